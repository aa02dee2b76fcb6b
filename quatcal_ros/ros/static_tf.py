"""
The result on /tf_static (publish_tf:=true): tf2_ros's static broadcaster, when installed.

tf2_ros comes with a ROS 2 install, not with the PyPI wheels: without it `StaticTf` says so
once (a WARN) and keeps the reason for /diagnostics; the result is on ~/transform either way.
"""

TF2_ROS_MISSING = ('publish_tf is true but tf2_ros is not installed: the result is not '
                   'broadcast on /tf_static (it is still on ~/transform)')


class StaticTf:
    """The /tf_static output of a node: made on demand, with its state in words."""

    def __init__(self, node):
        self.node = node
        self.broadcaster = None   # tf2_ros.StaticTransformBroadcaster once started
        self.problem = None       # why publish_tf has no effect

    def start(self):
        """Make the broadcaster (once); return whether it exists."""
        if self.broadcaster is not None:
            return True
        try:
            import tf2_ros
        except ImportError:
            if self.problem is None:
                self.node.get_logger().warning(TF2_ROS_MISSING)
            self.problem = TF2_ROS_MISSING
            return False
        self.problem = None
        self.broadcaster = tf2_ros.StaticTransformBroadcaster(self.node)
        return True

    def send(self, transform):
        """Broadcast `transform` (TransformStamped), when the broadcaster exists."""
        if self.broadcaster is not None:
            self.broadcaster.sendTransform(transform)

    def state(self, enabled):
        """Return the broadcast state for /diagnostics, and the problem to name (or None)."""
        if not enabled:
            return 'off (publish_tf is false)', None
        if self.problem:
            return 'not broadcast: tf2_ros is not installed', self.problem
        return 'broadcast', None
