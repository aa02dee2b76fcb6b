"""
QoS profiles shared by the package's nodes and tools.

LATCHED_QOS is the profile of a result that late subscribers must still get (the estimate,
the simulated cell's ground truth): reliable, transient local, depth 1, at both ends.
"""

from rclpy.qos import DurabilityPolicy
from rclpy.qos import HistoryPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy

LATCHED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
