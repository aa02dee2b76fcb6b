"""
QoS profiles shared by the package's nodes and tools, one place for each.

LATCHED_QOS is the profile of a result that late subscribers must still get (the estimate,
the simulated cell's ground truth): reliable, transient local, depth 1, at both ends.
The TF profiles are tf2's: /tf reliable, depth 100; /tf_static transient local, so every
static broadcaster's latched message arrives whenever it started.
"""

from rclpy.event_handler import PublisherEventCallbacks
from rclpy.qos import DurabilityPolicy
from rclpy.qos import HistoryPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy

LATCHED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

# Pose topics in. Depth 1000: one second of a 1 kHz stream (or of a flood of bad messages)
# waits while a new sample is estimated instead of being dropped.
LINK_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)
# BEST_EFFORT matches reliable and best-effort (sensor data) publishers alike.
SENSOR_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.BEST_EFFORT)
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC_LISTEN_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL)
TF_STATIC_BROADCAST_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def quiet_publisher_events():
    """
    Return publisher event callbacks without rclpy's defaults, for the node's outputs.

    The defaults (a warning on an incompatible subscriber) are two waitables per publisher
    that the executor polls on every message: for the calibrator's outputs, whose QoS every
    usual subscriber matches, that cost the 1 kHz input path more than it told anyone.
    """
    return PublisherEventCallbacks(use_default_callbacks=False)
