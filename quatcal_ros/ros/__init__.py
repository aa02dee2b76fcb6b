"""
The ROS 2 side.

Message conversions, rosbag2 files, parameters, QoS and the nodes (rclpy, message packages,
rosbags).
"""
