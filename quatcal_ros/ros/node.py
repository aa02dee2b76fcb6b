"""
The live calibrator node: pose topics in, hand-eye estimate out (DESIGN.md contract 4).

A thin shell: the session (stream/session.py) does the work, and this node wires it to ROS.
- subscribes `link_pose` and `sensor_pose` (relative names; PoseStamped, or TransformStamped
  with pose_type:=transform); each message is checked, converted and counted by
  pose_screen.PoseScreen, the same checks the replay runs; bad ones are logged throttled;
- publishes `~/rotation` (QuaternionStamped, latched, frame_id = link_frame) and
  `~/transform` (TransformStamped link_frame -> sensor_frame, latched) on each new estimate,
  with publish_tf:=true also on /tf_static (frame-safe), and the status on
  `/diagnostics` (diagnostics.py) every diagnostics_period_s;
- serves `~/capture`, `~/reset` and `~/save` (std_srvs/Trigger);
- keeps the session's files and warnings through files/session_record.py: each captured
  sample goes to the samples journal before its estimate is published and is fsync'd before it
  is logged; resume:=true continues a journal; a moved marker is warned of once;
- declares its parameters from the settings table (parameters.py) and re-estimates from the
  samples kept when one that shapes the session changes at runtime.

Times come from header stamps and the node clock (so use_sim_time and bag replays work).
"""

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import QuaternionStamped
from geometry_msgs.msg import TransformStamped
from quatcal_ros.core.pose import Pose
from quatcal_ros.files import exports
from quatcal_ros.files import journal
from quatcal_ros.files.session_record import MoveWatch, SamplesJournal, save_result
from quatcal_ros.ros import conversions
from quatcal_ros.ros import parameters
from quatcal_ros.ros import spin
from quatcal_ros.ros.diagnostics import calibrator_status, describe_result, InputWatch
from quatcal_ros.ros.pose_screen import PoseScreen
from quatcal_ros.ros.qos import LATCHED_QOS
from quatcal_ros.ros.static_tf import StaticTf
from quatcal_ros.ros.tf_feed import TfFeed
from quatcal_ros.stream import message_checks
from quatcal_ros.stream import settings
from quatcal_ros.stream.session import EstimateUpdated, Notice, Rejected, SampleCaptured
from quatcal_ros.stream.session import Session
from quatcal_ros.stream.settings import ConfigError
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from rclpy.qos import HistoryPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

NODE_NAME = settings.NODE_NAME
LINK, SENSOR = message_checks.LINK, message_checks.SENSOR
LOG_THROTTLE_S = message_checks.LOG_THROTTLE_S
# Depth 1000: one second of a 1 kHz stream (or of a flood of bad messages) waits while a new
# sample is estimated instead of being dropped.
LINK_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)
# BEST_EFFORT matches reliable and best-effort (sensor data) publishers alike.
SENSOR_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.BEST_EFFORT)
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# TF input: tf2's listener QoS (reliable, depth 100; /tf_static transient local, so every
# static broadcaster's latched message arrives whenever it started).
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)


class CalibratorNode(Node):
    """The `calibrator` node (module docstring); raises ConfigError on bad parameters."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        try:
            self.config = parameters.declare_parameters(self)
            self._tf_frames = settings.tf_frames(self.config)
            self.journal = SamplesJournal(self.config.samples_file, self._journal_header(),
                                          self.config.resume)
        except (journal.JournalRefused, OSError) as error:
            self.destroy_node()
            raise ConfigError(f'samples_file {self.config.samples_file}: {error}') from None
        except ConfigError:
            self.destroy_node()
            raise
        self.session = Session(settings.session_config(self.config))
        self.poses = PoseScreen(settings.check_config(self.config), self._log_bad_message)
        self.moves = MoveWatch()
        self._rejected_samples = set()
        self.tf = None
        message_type = self._subscribe_inputs()
        self.rotation_publisher = self.create_publisher(
            QuaternionStamped, '~/rotation', LATCHED_QOS)
        self.transform_publisher = self.create_publisher(
            TransformStamped, '~/transform', LATCHED_QOS)
        self.static_tf = StaticTf(self)
        self.diagnostics_publisher = self.create_publisher(
            DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        # On the node clock (with use_sim_time: one status per second of a played bag); a
        # steady-clock watch keeps it coming, saying so, when that clock stands still.
        self.create_timer(self.config.diagnostics_period_s, self.publish_diagnostics)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._last_status_ns = self._steady.now().nanoseconds
        self.create_timer(self.config.diagnostics_period_s, self._watch_status,
                          clock=self._steady)
        self.create_service(Trigger, '~/capture', self._on_capture)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save', self._on_save)
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(
            f'calibrating {self.config.setup} rotation {self.config.link_frame} -> '
            f'{self.config.sensor_frame} from {self._input_text()} '
            f'({message_type.__name__}), capture mode {self.config.capture_mode}')
        self._start_tf_broadcast()
        package = 'tf2_msgs' if self.tf is not None else 'geometry_msgs'
        self.inputs = InputWatch(f'{package}/msg/{message_type.__name__}', self.now_ns())
        self._resume()

    @property
    def stats(self):
        """Return the message counts (message_checks.StreamStats)."""
        return self.poses.stats

    @property
    def checks(self):
        """Return what pose messages must satisfy (message_checks.CheckConfig)."""
        return self.poses.config

    def now_ns(self):
        """Return the node clock (ROS time; simulated with use_sim_time) in nanoseconds."""
        return self.get_clock().now().nanoseconds

    # --- pose input ------------------------------------------------------------------------

    def _subscribe_inputs(self):
        """Subscribe the pose topics, or /tf and /tf_static (TF input); return the type."""
        frames = self._tf_frames
        if frames is None:
            message_type = PoseStamped if self.config.pose_type == 'pose' else TransformStamped
            self.topics = {   # resolved names (namespace, remapping), for the logs
                stream: self.create_subscription(message_type, stream, callback, qos).topic_name
                for stream, callback, qos in ((LINK, self._on_link, LINK_QOS),
                                              (SENSOR, self._on_sensor, SENSOR_QOS))}
            return message_type
        self.tf = TfFeed(TfFeed.new_tree(), self.poses, frames, self._on_tf_pose)
        tf_topic = self.create_subscription(
            TFMessage, '/tf', lambda msg: self._on_tf(tf_topic.topic_name, msg, False),
            TF_QOS)
        static_topic = self.create_subscription(
            TFMessage, '/tf_static', lambda msg: self._on_tf(static_topic.topic_name, msg, True),
            TF_STATIC_QOS)
        self.topics = {LINK: tf_topic.topic_name, SENSOR: tf_topic.topic_name}
        return TFMessage

    def _input_text(self):
        if self.tf is None:
            return f'{self.topics[LINK]} and {self.topics[SENSOR]}'
        pairs = {stream: f'{frames.target} -> {frames.source}'
                 for stream, frames in self.tf.watchers.items()}
        return f'/tf and /tf_static: link pose {pairs[LINK]}, sensor pose {pairs[SENSOR]}'

    def _on_tf(self, topic, msg, static):
        self.poses.stats.note(topic, self.now_ns())
        self.tf.take(topic, msg, static)

    def _on_tf_pose(self, stream, stamp_ns, pose):
        """Take a pose composed from the transform tree (TF input), as _on_pose does."""
        now_ns = self.now_ns()
        self.poses.take_rows(stream, 1, now_ns)
        add = self.session.add_link_pose if stream == LINK else self.session.add_sensor_pose
        self._add_pose(stream, add, (stamp_ns, pose), now_ns)

    def _on_link(self, msg):
        self._on_pose(LINK, msg, self.session.add_link_pose)

    def _on_sensor(self, msg):
        self._on_pose(SENSOR, msg, self.session.add_sensor_pose)

    def _on_pose(self, stream, msg, add):
        now_ns = self.now_ns()
        taken = self.poses.take(stream, msg, now_ns)
        if taken is not None:
            self._add_pose(stream, add, taken, now_ns)

    def _add_pose(self, stream, add, taken, now_ns):
        """Give a checked (stamp_ns, Pose) to the session; handle what it says."""
        events = self.poses.verdict(stream, add(*taken), now_ns)
        if events:
            self.handle_events(events)

    def _log_bad_message(self, stream, reason, count, detail):
        total = self.poses.stats.bad[stream, reason]
        so_far = (f'{total} so far' if count == total
                  else f'{count} since the last report, {total} in all')
        self.get_logger().warning(
            f'{self.topics.get(stream, stream)}: bad message skipped ({reason}, {so_far}; '
            'reported at most '
            f'every {LOG_THROTTLE_S:g} s): {message_checks.detail_text(detail)}')

    # --- session events --------------------------------------------------------------------

    def handle_events(self, events):
        """
        Journal new samples, publish each new estimate, then log the session's events.

        The journal comes first: a sample is in the file (safe from a crash of the process)
        before the estimate is published, and fsync'd (safe from a power cut) before it is
        reported captured. The log lines come last; then the session is asked for the estimate
        of the new samples, whose events are handled the same way.
        """
        captured = [event.sample for event in events if isinstance(event, SampleCaptured)]
        self._log_messages(self.journal.append(captured, self.session.samples))
        for event in events:
            if isinstance(event, EstimateUpdated):
                self.publish_estimate(event.result)
        if captured:
            self._log_messages(self.journal.sync())
        for event in events:
            if isinstance(event, SampleCaptured):
                self._log_sample(event)
            elif isinstance(event, EstimateUpdated):
                self._log_estimate(event.result)
            elif isinstance(event, Rejected):
                self.get_logger().info(f'rejected {event.what}: {event.reason}',
                                       throttle_duration_sec=LOG_THROTTLE_S)
            elif isinstance(event, Notice) and event.code == 'time_jump':
                self.get_logger().info(event.text, throttle_duration_sec=LOG_THROTTLE_S)
            elif isinstance(event, Notice):
                self.get_logger().info(event.text)
        # The estimate of new samples, if any (the session estimates when asked).
        later = self.session.estimate()
        if later:
            self.handle_events(later)

    def _log_sample(self, event):
        position = ', '.join(f'{v:.3f}' for v in event.sample.link.position)
        self.get_logger().info(f'sample {event.index} captured at stamp '
                               f'{event.sample.stamp_ns * 1e-9:.3f} s (link at [{position}] m)')

    def publish_estimate(self, result):
        """Publish `result` (quaternion, translation) on ~/rotation, ~/transform, /tf_static."""
        msg = conversions.quaternion_stamped_msg(
            result.quaternion, self.now_ns(), self.config.link_frame)
        self.rotation_publisher.publish(msg)
        stamp_ns = conversions.stamp_ns_from_header(msg.header)
        self.transform_publisher.publish(self.transform_msg(result, stamp_ns))
        if self.config.publish_tf:
            self._broadcast(result, stamp_ns)

    def transform_msg(self, result, stamp_ns):
        """Return the TransformStamped link_frame -> sensor_frame of `result`."""
        return conversions.transform_stamped_msg(
            Pose.create(result.translation, result.quaternion), stamp_ns,
            self.config.link_frame, self.config.sensor_frame)

    def _log_estimate(self, result):
        """Log a new estimate, its newly rejected samples and warnings, and a moved marker."""
        logger = self.get_logger()
        logger.info(describe_result(result))
        rejected = {entry['sample']: entry['reason'] for entry in result.rejected
                    if 'sample' in entry}
        for index in sorted(set(rejected) - self._rejected_samples):
            logger.info(f'rejected sample {index}: {rejected[index]}')
        self._rejected_samples = set(rejected)
        for warning in result.warnings:
            logger.warning(warning, throttle_duration_sec=LOG_THROTTLE_S)
        options = self.session.config.calibration
        move = self.moves.check(self.session.samples, result.quaternion, options.setup,
                                options.invert_sensor)
        if move:
            logger.warning(move)

    def _log_messages(self, messages):
        logger = self.get_logger()
        for level, text in messages:   # one call site per severity (rclpy insists)
            if level == 'error':
                logger.error(text)
            elif level == 'warning':
                logger.warning(text)
            else:
                logger.info(text)

    def _start_tf_broadcast(self):
        """With publish_tf, start /tf_static; turned on at runtime, it sends the estimate."""
        result = self.session.result
        if self.config.publish_tf and self.static_tf.start() and result is not None:
            self._broadcast(result, self.now_ns())

    def _broadcast(self, result, stamp_ns):
        """Put the result on /tf_static, frame-safe in the TF tree with TF input."""
        self.static_tf.send(Pose.create(result.translation, result.quaternion), stamp_ns,
                            self.config.link_frame, self.config.sensor_frame,
                            self.tf.tree if self.tf is not None else None)

    # --- samples journal -------------------------------------------------------------------

    def _journal_header(self):
        return journal.JournalHeader(self.config.setup, self.config.link_frame,
                                     self.config.sensor_frame)

    def _resume(self):
        """Log what opening the journal did; estimate from its samples when resuming."""
        report = self.journal.report
        self._log_messages(report.messages)
        if report.samples:   # already in the journal: not appended again, not logged
            self._add_known_samples(report.samples)
            if self.session.result is None:
                self.get_logger().info(f'no estimate from the resumed samples yet: '
                                       f'{self.session.last_error}')

    def _add_known_samples(self, samples):
        events = self.session.add_samples(samples)
        self.handle_events([e for e in events if not isinstance(e, SampleCaptured)])

    def destroy_node(self):
        """Close the samples journal (releasing its lock), then destroy the node."""
        if getattr(self, 'journal', None) is not None:
            self.journal.close()
            self.journal = None
        return super().destroy_node()

    # --- diagnostics -----------------------------------------------------------------------

    def diagnostic_status(self):
        """Build the DiagnosticStatus published on /diagnostics."""
        tf_static, tf_problem = self.static_tf.state(self.config.publish_tf)
        now_ns = self.now_ns()
        problems = [self.moves.warning(len(self.session.samples)), self.journal.problem,
                    tf_problem, *self.inputs.problems(
                        self.poses.stats, self.topics, self._publisher_types,
                        self.session.counters['time_jumps'], now_ns,
                        self.get_parameter('use_sim_time').value),
                    *(self.tf.problems() if self.tf is not None else ())]
        return calibrator_status(self.session, self.poses.stats, now_ns,
                                 self.config.link_frame, problems, tf_static,
                                 self.inputs.started_ns, self.topics)

    def _publisher_types(self, topic):
        return [info.topic_type for info in self.get_publishers_info_by_topic(topic)]

    def _watch_status(self):
        """Publish the status when the node clock has not for two periods (no /clock)."""
        late_ns = 2 * self.config.diagnostics_period_s * 1e9
        if self._steady.now().nanoseconds - self._last_status_ns > late_ns:
            self.publish_diagnostics()

    def publish_diagnostics(self):
        """Publish the status once (the timer's callback)."""
        self._last_status_ns = self._steady.now().nanoseconds
        array = DiagnosticArray(status=[self.diagnostic_status()])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_publisher.publish(array)

    # --- services --------------------------------------------------------------------------

    def _on_capture(self, request, response):
        ok, reason = self.session.capture(self.now_ns())
        self.handle_events(self.session.pop_events())
        if not ok:
            self.get_logger().info(f'capture refused: {reason}')
        response.success, response.message = bool(ok), reason
        return response

    def _on_reset(self, request, response):
        discarded = len(self.session.samples)
        self.session.reset()
        self._rejected_samples = set()
        self.moves.reset()
        journal_text = self.journal.restart()
        if self.journal.problem:
            self.get_logger().error(self.journal.problem)
        response.success = True
        response.message = (f'session cleared: {discarded} samples discarded (the last '
                            f'~/rotation stays latched until a new estimate){journal_text}')
        self.get_logger().info(response.message)
        return response

    def _on_save(self, request, response):
        result = self.session.result
        if result is None:
            response.success = False
            response.message = f'no estimate yet, nothing saved: {self.session.last_error}'
            return response
        config = self.config
        frames = (config.link_frame, config.sensor_frame)
        # The link poses' header frame is the robot base (eye_in_hand); '' when not checked.
        base = {'robot_base_frame': config.link_frame_id} if config.setup == 'eye_in_hand' else {}
        saved = save_result(result, frames, config.setup, config.result_file,
                            config.easy_handeye2_file, base)
        response.success, response.message = saved.ok, '; '.join(saved.texts())
        if not saved.ok:
            self.get_logger().error(response.message)
        if saved.ok:
            self.get_logger().info(f'result {response.message}')
            self.get_logger().info(
                'to broadcast the result on /tf_static: '
                + exports.static_transform_publisher_command(result, *frames))
        return response

    # --- parameters at runtime -------------------------------------------------------------

    def _check_parameters(self, changes):
        try:
            parameters.updated(self.config, changes)
        except ConfigError as error:
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, changes):
        old, self.config = self.config, parameters.updated(self.config, changes)
        self.poses.config = settings.check_config(self.config)
        changed = [n for n, v in self.config.as_dict().items() if old.as_dict()[n] != v]
        if changed:
            self.get_logger().info(f'parameters changed: {", ".join(changed)}')
        if set(changed) & set(journal.HEADER_KEYS):
            self._log_messages(self.journal.set_header(self._journal_header()))
        if 'publish_tf' in changed:
            self._start_tf_broadcast()
        if any(name not in settings.PRESENTATION for name in changed):
            samples = self.session.samples
            self.session = Session(settings.session_config(self.config))
            if samples:
                self.get_logger().info(
                    f're-estimating from the {len(samples)} samples with the new settings')
                self._add_known_samples(samples)


def main(args=None):
    """Run the calibrator node; return 2 (after logging the reason) for invalid parameters."""
    return spin.run(CalibratorNode, NODE_NAME, ConfigError, 'invalid parameters', args)


if __name__ == '__main__':
    raise SystemExit(main())
