"""
The live node's pose input: two pose topics, or /tf and /tf_static (DESIGN.md contract 4).

`NodeInputs` makes the subscriptions and turns every message into checked (stamp_ns, Pose)
pairs through one PoseScreen, the checks the replay runs too:
- pose topics `link_pose` and `sensor_pose` (relative names; PoseStamped, TransformStamped
  with pose_type:=transform, PoseWithCovarianceStamped with pose_type:=pose_with_covariance);
- with the four TF frames set (settings.tf_frames), /tf and /tf_static through a TfFeed that
  composes base -> effector and tracking base -> marker at each stamp;
- with sensor_input:=image, camera images on `image` (or `image/compressed`) and
  `camera_info`: the board's pose in each (image_input.ImageInput), the link pose from its
  topic or from TF (robot_base_frame -> robot_effector_frame).
Each good pose goes to `deliver(stream, (stamp_ns, pose), now_ns)`; a bad message is logged,
throttled, with its resolved topic name.

PoseStamped and TransformStamped topics are taken raw: their bytes are decoded here, and only a
message the decoder does not vouch for is deserialised by rclpy and checked as a message. The
checks and the counts are the same either way; what is saved is the message objects of every
1 kHz link pose, and most of the per-message Python. The link stream's bytes are held
(`LINK_BATCH` at most, none older than `LINK_BATCH_AGE_NS`) and decoded together
(cdr.decode_poses) when any other input, service or timer of the node comes, or the batch is
full (`flush`): every pose still reaches the session in arrival order, before anything that
arrived after it. The sensor stream's are decoded one by one (cdr.decode_pose).
"""

import time

from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import PoseWithCovarianceStamped
from geometry_msgs.msg import TransformStamped
from quatcal_ros.ros import cdr
from quatcal_ros.ros.conversions import frame_ids, pose_from_values
from quatcal_ros.ros.image_input import ImageInput
from quatcal_ros.ros.pose_screen import PoseScreen
from quatcal_ros.ros.qos import LINK_QOS, SENSOR_QOS, TF_QOS, TF_STATIC_LISTEN_QOS
from quatcal_ros.ros.tf_feed import TfFeed
from quatcal_ros.stream import message_checks
from quatcal_ros.stream.log_throttle import LOG_THROTTLE_S
from quatcal_ros.stream.message_checks import LINK, SENSOR
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos import ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from tf2_msgs.msg import TFMessage

# The pose_type setting's choices (settings.POSE_TYPES).
MESSAGE_TYPES = {'pose': PoseStamped, 'transform': TransformStamped,
                 'pose_with_covariance': PoseWithCovarianceStamped}
PACKAGES = {PoseStamped: 'geometry_msgs', TransformStamped: 'geometry_msgs',
            PoseWithCovarianceStamped: 'geometry_msgs', TFMessage: 'tf2_msgs',
            Image: 'sensor_msgs', CompressedImage: 'sensor_msgs'}
# The types taken raw and decoded by cdr (module docstring).
RAW_TYPES = {PoseStamped: 'geometry_msgs/msg/PoseStamped',
             TransformStamped: 'geometry_msgs/msg/TransformStamped'}
# Raw link messages held before they are decoded together: at most this many (16 ms at 1 kHz),
# and none held past the next arrival once it is this old (steady clock).
LINK_BATCH = 16
LINK_BATCH_AGE_NS = 10_000_000


class NodeInputs:
    """The subscriptions of the calibrator node and the checks of what they bring."""

    def __init__(self, node, check_config, tf_frames, pose_types, deliver, images=None,
                 deliver_rows=None):
        """
        Subscribe on `node`: the TF topics for the streams `tf_frames` names, else pose topics.

        :param check_config: message_checks.CheckConfig, what the messages must satisfy.
        :param tf_frames: settings.tf_frames(config): {stream: frame pair} or None.
        :param pose_types: {stream: a key of MESSAGE_TYPES}.
        :param deliver: deliver(stream, (stamp_ns, Pose), now_ns) for each good pose.
        :param images: (vision.image_sensor.ImageSensor, transport 'raw' or 'compressed',
            on_new_camera()): the sensor poses come from camera images (sensor_input:=image),
            or None.
        :param deliver_rows: deliver_rows(stream, stamps_ns, positions, quaternions_wxyz,
            now_ns) for a run of good poses decoded together (Session.add_poses' arguments).
        """
        self._node = node
        self._deliver = deliver
        self._deliver_rows = deliver_rows
        self._held = []          # raw link messages not decoded yet (module docstring)
        self._held_since_ns = 0  # steady clock at the first of them
        self._held_last_ns = 0   # and at the last: when the batch came, however late flushed
        self._held_kind = None
        # {stream: (header.frame_id, child frame or None)} of its first message since the node
        # last cleared it (pose topics and images), for stream.frame_notices
        self.frames_seen = {}
        self.screen = PoseScreen(check_config, self._log_bad_message)
        # The pose subscriptions, and the publishers (their gids) of those whose topic has
        # one: its publication sequence numbers count the messages lost (check_publishers).
        # Not the images, whose sensor-data queue of 5 drops frames by design.
        self._numbered = {}
        self._counted = {}
        tf_frames = tf_frames or {}
        self.message_types, self.topics = {}, {}
        self.reliable = set()   # the streams subscribed reliable: best-effort publishers miss
        self.composed = frozenset(tf_frames)   # the streams composed from /tf's frames
        self.tf = None
        self.images = None
        if tf_frames:
            self.tf = TfFeed(TfFeed.new_tree(), self.screen, tf_frames, self._on_tf_pose,
                             link=LINK, sensor=SENSOR)
            tf_topic = node.create_subscription(
                TFMessage, '/tf', lambda msg: self._on_tf(tf_topic.topic_name, msg, False),
                TF_QOS)
            static_topic = node.create_subscription(
                TFMessage, '/tf_static',
                lambda msg: self._on_tf(static_topic.topic_name, msg, True),
                TF_STATIC_LISTEN_QOS)
            for stream in tf_frames:
                self.message_types[stream] = TFMessage
                self.topics[stream] = tf_topic.topic_name
                self.reliable.add(stream)
        if images is not None:
            self._subscribe_images(*images)
        for stream, qos in ((LINK, LINK_QOS), (SENSOR, SENSOR_QOS)):
            if stream not in self.topics:
                kind = self.message_types[stream] = MESSAGE_TYPES[pose_types[stream]]
                if kind in RAW_TYPES and stream == LINK and deliver_rows is not None:
                    self._held_kind = kind
                    take = self._hold_link
                elif kind in RAW_TYPES:
                    take = (lambda raw, s=stream, k=kind: self._on_raw_pose(s, raw, k))
                else:
                    take = (lambda msg, s=stream: self._on_pose(s, msg))
                subscription = self._numbered[stream] = node.create_subscription(
                    kind, stream, self._sequenced(stream, take), qos, raw=kind in RAW_TYPES)
                self.topics[stream] = subscription.topic_name   # resolved name, for logs
                if qos.reliability == ReliabilityPolicy.RELIABLE:
                    self.reliable.add(stream)

    def _subscribe_images(self, sensor, transport, on_new_camera):
        """Take the sensor stream from camera images and camera_info (sensor-data QoS)."""
        self.images = ImageInput(sensor, self.screen,
                                 lambda text: self._node.get_logger().warning(text),
                                 on_new_camera)
        kind = CompressedImage if transport == 'compressed' else Image
        self.message_types[SENSOR] = kind
        self.topics[SENSOR] = self._node.create_subscription(
            kind, 'image/compressed' if transport == 'compressed' else 'image',
            self._on_image, qos_profile_sensor_data).topic_name
        self.camera_info_topic = self._node.create_subscription(
            CameraInfo, 'camera_info', self._on_camera_info,
            qos_profile_sensor_data).topic_name
        self.images.camera_info_topic = self.camera_info_topic

    @property
    def type_names(self):
        """Return each stream's message type, e.g. {'link_pose': 'geometry_msgs/msg/...'}."""
        return {stream: f'{PACKAGES[kind]}/msg/{kind.__name__}'
                for stream, kind in self.message_types.items()}

    def describe(self):
        """Return where the poses come from, in words (for the start-up log line)."""
        kinds = [self.message_types[stream] for stream in (LINK, SENSOR)]
        if kinds == [TFMessage, TFMessage]:
            pairs = {stream: f'{frames.target} -> {frames.source}'
                     for stream, frames in self.tf.watchers.items()}
            return (f'/tf and /tf_static: link pose {pairs[LINK]}, sensor pose {pairs[SENSOR]} '
                    '(TFMessage)')
        if self.tf is None and self.images is None:
            link, sensor = (kind.__name__ for kind in kinds)
            names = link if link == sensor else f'{link}, {sensor}'
            return f'{self.topics[LINK]} and {self.topics[SENSOR]} ({names})'
        if self.tf is not None:
            frames = self.tf.watchers[LINK]
            link = f'/tf and /tf_static ({frames.target} -> {frames.source})'
        else:
            link = f'{self.topics[LINK]} ({kinds[0].__name__})'
        board = self.images.sensor.board
        return (f'link pose {link}, sensor pose: a {board.kind} board '
                f'({board.size[0]} x {board.size[1]}) in {self.topics[SENSOR]} '
                f'({kinds[1].__name__}) with {self.camera_info_topic}')

    def _sequenced(self, stream, take):
        """
        Return the callback (message, message info) of `stream`: take(message).

        On a topic with one publisher, first counts the messages missing before it from the
        publication sequence number and the publisher's stamp (StreamStats.note_sequence;
        None where the middleware does not give one).
        """
        counted, screen = self._counted, self.screen

        def callback(msg, info):
            if stream in counted:
                sequence = info.get('publication_sequence_number')
                if sequence is not None:
                    screen.stats.note_sequence(stream, sequence, info.get('source_timestamp'))
            take(msg)
        return callback

    def check_publishers(self):
        """
        Count lost messages on the topics with one publisher only; call it now and then.

        Two publishers' sequence numbers interleave, and rclpy does not say whose a message
        is: a stream whose publishers changed (another gid) starts its sequence afresh, and
        one whose numbers went back since the last check (StreamStats.note_sequence) too.
        A publisher replaced between two checks can still count the messages it sent before
        the node heard it.
        """
        stats = self.screen.stats
        for stream, subscription in self._numbered.items():
            heard = self._node.get_publishers_info_by_topic(subscription.topic_name)
            gids = tuple(bytes(info.endpoint_gid) for info in heard)
            if len(gids) != 1:
                self._counted.pop(stream, None)
                continue
            stats.restart_sequence(stream, always=self._counted.get(stream) != gids)
            self._counted[stream] = gids

    def problems(self, result=None):
        """
        Return the TF frame pairs that cannot be composed, in words (none for pose topics).

        result: the latest estimate, or None (TfFeed.swapped_frames).
        """
        return self.tf.problems(result) if self.tf is not None else []

    def _on_pose(self, stream, msg):
        if stream != LINK:
            self.flush()
        if stream not in self.frames_seen:
            self.frames_seen[stream] = frame_ids(msg)
        now_ns = self._node.now_ns()
        taken = self.screen.take(stream, msg, now_ns)
        if taken is not None:
            self._deliver(stream, taken, now_ns)

    def flush(self):
        """Decode and deliver the link messages held (module docstring); call before others."""
        held = self._held
        if not held:
            return
        self._held = []
        kind = self._held_kind
        checks = self.screen.config
        decoded = cdr.decode_poses(held, RAW_TYPES[kind], frame_id=checks.frame_id(LINK),
                                   max_position_m=checks.max_position_m)
        # The node clock when the batch's last message came: a batch the status timer flushes
        # (the streams stopped) waited up to a period, which is no latency of the poses.
        now_ns = self._node.now_ns() - max(0, time.monotonic_ns() - self._held_last_ns)
        ok = decoded.ok & message_checks.stamps_usable(decoded.stamps_ns, now_ns,
                                                       checks.max_stamp_offset_ns)
        for start, stop, good in cdr.stretches(ok):
            if not good:   # each one checked and counted as a message, with its reason
                for raw in held[start:stop]:
                    self._on_raw_pose(LINK, raw, kind)
                continue
            self.screen.take_rows(LINK, stop - start, now_ns)
            self._deliver_rows(LINK, decoded.stamps_ns[start:stop].tolist(),
                               decoded.positions[start:stop], decoded.quaternions[start:stop],
                               now_ns)

    def _hold_link(self, raw):
        if LINK not in self.frames_seen:
            self._note_raw_frames(LINK, raw, self._held_kind)
        now = time.monotonic_ns()
        if not self._held:
            self._held_since_ns = now
        self._held_last_ns = now
        self._held.append(raw)
        if len(self._held) >= LINK_BATCH or now - self._held_since_ns >= LINK_BATCH_AGE_NS:
            self.flush()

    def _on_raw_pose(self, stream, raw, kind):
        """Take a raw pose message: decoded here when cdr vouches for it, else by rclpy."""
        if stream != LINK:
            self.flush()
        if stream not in self.frames_seen:
            self._note_raw_frames(stream, raw, kind)
        decoded = cdr.decode_pose(raw, RAW_TYPES[kind])
        pose = None if decoded is None else pose_from_values(*decoded[2])
        if pose is None:
            try:
                msg = deserialize_message(raw, kind)
            except Exception as error:   # rclpy raises its own error types for bad bytes
                self.screen.stats.note(stream, self._node.now_ns())
                self.screen.bad(stream, 'undecodable', f'{len(raw)} bytes: {error}')
                return
            self._on_pose(stream, msg)
            return
        now_ns = self._node.now_ns()
        taken = self.screen.take_decoded(stream, decoded[0], decoded[1], pose, now_ns)
        if taken is not None:
            self._deliver(stream, taken, now_ns)

    def _note_raw_frames(self, stream, raw, kind):
        """Keep the frames of a raw message in `frames_seen` (not yet when cdr cannot read it)."""
        frames = cdr.frame_ids(raw, RAW_TYPES[kind])
        if frames is not None:
            self.frames_seen[stream] = frames

    def _on_camera_info(self, msg):
        self.flush()
        taken = self.images.take_camera_info(msg)
        if taken is not None:   # the image held for the first camera_info
            self._deliver(SENSOR, taken, self._node.now_ns())

    def _on_image(self, msg):
        self.flush()
        if SENSOR not in self.frames_seen:
            self.frames_seen[SENSOR] = frame_ids(msg)
        now_ns = self._node.now_ns()
        taken = self.images.take_image(msg, now_ns)
        if taken is not None:
            self._deliver(SENSOR, taken, now_ns)

    def _on_tf(self, topic, msg, static):
        self.flush()
        now_ns = self._node.now_ns()
        self.screen.stats.note(topic, now_ns)
        self.tf.take(topic, msg, static, now_ns)

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
