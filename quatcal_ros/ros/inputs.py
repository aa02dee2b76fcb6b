"""
The live node's pose input: two pose topics, or /tf and /tf_static (DESIGN.md contract 4).

`NodeInputs` makes the subscriptions and turns every message into checked (stamp_ns, Pose)
pairs through one PoseScreen, the checks the replay runs too:
- pose topics `link_pose` and `sensor_pose` (relative names; PoseStamped, TransformStamped
  with pose_type:=transform, PoseWithCovarianceStamped with pose_type:=pose_with_covariance);
- with the four TF frames set (settings.tf_frames), /tf and /tf_static through a TfFeed that
  composes base -> effector and tracking base -> marker at each stamp.
Each good pose goes to `deliver(stream, (stamp_ns, pose), now_ns)`; a bad message is logged,
throttled, with its resolved topic name.
"""

from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import PoseWithCovarianceStamped
from geometry_msgs.msg import TransformStamped
from quatcal_ros.ros.pose_screen import PoseScreen
from quatcal_ros.ros.qos import LINK_QOS, SENSOR_QOS, TF_QOS, TF_STATIC_LISTEN_QOS
from quatcal_ros.ros.tf_feed import TfFeed
from quatcal_ros.stream import message_checks
from quatcal_ros.stream.message_checks import LINK, LOG_THROTTLE_S, SENSOR
from tf2_msgs.msg import TFMessage

# The pose_type setting's choices (settings.POSE_TYPES).
MESSAGE_TYPES = {'pose': PoseStamped, 'transform': TransformStamped,
                 'pose_with_covariance': PoseWithCovarianceStamped}


class NodeInputs:
    """The subscriptions of the calibrator node and the checks of what they bring."""

    def __init__(self, node, check_config, tf_frames, pose_types, deliver):
        """
        Subscribe on `node`: the TF topics when `tf_frames` is set, else the pose topics.

        :param check_config: message_checks.CheckConfig, what the messages must satisfy.
        :param tf_frames: settings.tf_frames(config): {stream: frame pair} or None.
        :param pose_types: {stream: a key of MESSAGE_TYPES}.
        :param deliver: deliver(stream, (stamp_ns, Pose), now_ns) for each good pose.
        """
        self._node = node
        self._deliver = deliver
        self.screen = PoseScreen(check_config, self._log_bad_message)
        self.tf = None
        if tf_frames is None:
            self.message_types = {stream: MESSAGE_TYPES[pose_types[stream]]
                                  for stream in (LINK, SENSOR)}
            self.topics = {   # resolved names (namespace, remapping), for the logs
                stream: node.create_subscription(
                    self.message_types[stream], stream,
                    lambda msg, s=stream: self._on_pose(s, msg), qos).topic_name
                for stream, qos in ((LINK, LINK_QOS), (SENSOR, SENSOR_QOS))}
            return
        self.message_types = {LINK: TFMessage, SENSOR: TFMessage}
        self.tf = TfFeed(TfFeed.new_tree(), self.screen, tf_frames, self._on_tf_pose)
        tf_topic = node.create_subscription(
            TFMessage, '/tf', lambda msg: self._on_tf(tf_topic.topic_name, msg, False), TF_QOS)
        static_topic = node.create_subscription(
            TFMessage, '/tf_static', lambda msg: self._on_tf(static_topic.topic_name, msg, True),
            TF_STATIC_LISTEN_QOS)
        self.topics = {LINK: tf_topic.topic_name, SENSOR: tf_topic.topic_name}

    @property
    def type_names(self):
        """Return each stream's message type, e.g. {'link_pose': 'geometry_msgs/msg/...'}."""
        package = 'tf2_msgs' if self.tf is not None else 'geometry_msgs'
        return {stream: f'{package}/msg/{kind.__name__}'
                for stream, kind in self.message_types.items()}

    def describe(self):
        """Return where the poses come from, in words (for the start-up log line)."""
        if self.tf is None:
            link, sensor = (self.message_types[s].__name__ for s in (LINK, SENSOR))
            kinds = link if link == sensor else f'{link}, {sensor}'
            return f'{self.topics[LINK]} and {self.topics[SENSOR]} ({kinds})'
        pairs = {stream: f'{frames.target} -> {frames.source}'
                 for stream, frames in self.tf.watchers.items()}
        return (f'/tf and /tf_static: link pose {pairs[LINK]}, sensor pose {pairs[SENSOR]} '
                '(TFMessage)')

    def problems(self):
        """Return the TF frame pairs that cannot be composed, in words (none for pose topics)."""
        return self.tf.problems() if self.tf is not None else []

    def _on_pose(self, stream, msg):
        now_ns = self._node.now_ns()
        taken = self.screen.take(stream, msg, now_ns)
        if taken is not None:
            self._deliver(stream, taken, now_ns)

    def _on_tf(self, topic, msg, static):
        self.screen.stats.note(topic, self._node.now_ns())
        self.tf.take(topic, msg, static)

    def _on_tf_pose(self, stream, stamp_ns, pose):
        """Take a pose composed from the transform tree, counted as one row of its stream."""
        now_ns = self._node.now_ns()
        self.screen.take_rows(stream, 1, now_ns)
        self._deliver(stream, (stamp_ns, pose), now_ns)

    def _log_bad_message(self, stream, reason, count, detail):
        total = self.screen.stats.bad[stream, reason]
        so_far = (f'{total} so far' if count == total
                  else f'{count} since the last report, {total} in all')
        self._node.get_logger().warning(
            f'{self.topics.get(stream, stream)}: bad message skipped ({reason}, {so_far}; '
            f'reported at most every {LOG_THROTTLE_S:g} s): '
            f'{message_checks.detail_text(detail)}')
