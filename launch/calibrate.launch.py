"""
Start the calibrator on a cell whose poses are in TF (a real ROS 2 Jazzy install).

    ros2 launch quatcal_ros calibrate.launch.py \
        robot_base_frame:=base_link robot_effector_frame:=tool0 \
        tracking_base_frame:=camera_color_optical_frame tracking_marker_frame:=aruco_marker

The result is robot_effector_frame -> tracking_base_frame (eye_in_hand; with
setup:=eye_to_hand, robot_base_frame -> tracking_base_frame) on /calibrator/transform;
params_file gives every other parameter (default: the package's config/calibrator.yaml).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

FRAMES = (
    ('robot_base_frame', 'base_link', 'the robot base frame'),
    ('robot_effector_frame', 'tool0', 'the robot link the camera (or the marker) is on'),
    ('tracking_base_frame', 'camera_color_optical_frame', "the frame of the sensor's poses"),
    ('tracking_marker_frame', 'marker', 'the frame of the observed marker or board'),
)


def generate_launch_description():
    """Return the launch description: the four frames, setup and params_file as arguments."""
    arguments = [DeclareLaunchArgument(name, default_value=default, description=text)
                 for name, default, text in FRAMES]
    arguments += [
        DeclareLaunchArgument('setup', default_value='eye_in_hand',
                              description='eye_in_hand or eye_to_hand'),
        DeclareLaunchArgument('params_file', default_value=PathJoinSubstitution(
            [FindPackageShare('quatcal_ros'), 'config', 'calibrator.yaml']),
            description='parameters of the calibrator (YAML)'),
    ]
    frames = {name: LaunchConfiguration(name) for name, _, _ in FRAMES}
    # link_frame and sensor_frame are left unset: with TF input the result is named by the
    # TF frames of the setup, also after `ros2 param set /calibrator setup eye_to_hand`
    # (link_frame set to the effector had refused that change).
    node = Node(package='quatcal_ros', executable='calibrator', name='calibrator',
                output='screen', parameters=[LaunchConfiguration('params_file'), frames,
                                             {'setup': LaunchConfiguration('setup')}])
    return LaunchDescription(arguments + [node])
