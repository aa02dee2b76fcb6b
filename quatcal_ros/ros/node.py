"""
The live calibrator node: pose topics in, hand-eye rotation estimate out (DESIGN.md contract 4).

A thin shell around session.Session:
- subscribes `link_pose` and `sensor_pose` (relative names; PoseStamped, or TransformStamped
  with pose_type:=transform) and feeds the header stamps and poses to the session; bad
  messages (message_checks) are skipped, counted per stream and reason on /diagnostics and
  logged, throttled, with the topic and the reason;
- publishes `~/rotation` (QuaternionStamped, reliable + transient local, depth 1, frame_id =
  link_frame) and `~/transform` (TransformStamped link_frame -> sensor_frame, same QoS) on
  each new estimate (asked of the session after every new sample), and a status on
  `/diagnostics` at diagnostics_period_s;
- with publish_tf:=true, broadcasts the estimate on /tf_static (tf2_ros, when installed);
- serves `~/capture`, `~/reset` and `~/save` (std_srvs/Trigger); ~/save also writes
  easy_handeye2_file and logs the static_transform_publisher line;
- appends every captured sample to samples_file (journal.py) before publishing its estimate,
  fsync'd before logging it;
  resume:=true continues the session in it after a crash or restart, ~/reset moves it aside;
- warns when the newest samples disagree with the earlier ones (a moved marker, drift.py).

Messages are read only through conversions; quaternions in the core are (w, x, y, z).
Times come from header stamps and the node clock (so use_sim_time and bag replays work).
"""

from dataclasses import replace
import gc
import signal
import time

from diagnostic_msgs.msg import DiagnosticArray
from diagnostic_msgs.msg import DiagnosticStatus
from diagnostic_msgs.msg import KeyValue
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import QuaternionStamped
from geometry_msgs.msg import TransformStamped
import numpy as np
from quatcal_ros.core import drift
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.files import exports
from quatcal_ros.files import journal
from quatcal_ros.files import persistence
from quatcal_ros.ros import conversions
from quatcal_ros.ros import node_config
from quatcal_ros.ros.qos import LATCHED_QOS
from quatcal_ros.stream import message_checks
from quatcal_ros.stream.message_checks import StreamStats
from quatcal_ros.stream.session import EstimateUpdated
from quatcal_ros.stream.session import Notice
from quatcal_ros.stream.session import Rejected
from quatcal_ros.stream.session import SampleCaptured
from quatcal_ros.stream.session import Session
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from std_srvs.srv import Trigger

NODE_NAME = 'calibrator'
DIAGNOSTIC_NAME = 'calibrator: hand-eye rotation'
LINK, SENSOR = message_checks.LINK, message_checks.SENSOR
# A stream that has sent nothing usable for this long (node clock) is stale: diagnostics
# say WARN and name it.
STALE_AFTER_S = message_checks.STALE_AFTER_S
# An RMS motion residual above this (degrees) means inconsistent data: diagnostics say WARN.
HIGH_RESIDUAL_DEG = 1.0
LOG_THROTTLE_S = 5.0
# Parameters that change only the presentation or the message checks, not the session.
PRESENTATION_PARAMETERS = ('link_frame', 'sensor_frame', 'result_file', 'max_stamp_offset_s',
                           'link_frame_id', 'sensor_frame_id', 'easy_handeye2_file',
                           'publish_tf')
# Said once (WARN) and kept in /diagnostics when publish_tf is true but tf2_ros is missing.
TF2_ROS_MISSING = ('publish_tf is true but tf2_ros is not installed: the result is not '
                   'broadcast on /tf_static (it is still on ~/transform)')

# Depth 1000: one second of a 1 kHz stream (or of a flood of bad messages) waits while a new
# sample is estimated (tens of ms, more on a loaded machine) instead of being dropped.
LINK_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)
# BEST_EFFORT matches reliable and best-effort (sensor data) publishers alike.
SENSOR_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.BEST_EFFORT)
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def format_quaternion_xyzw(q_wxyz):
    """'x, y, z, w = (..)' text of a quaternion given as (w, x, y, z)."""
    x, y, z, w = quat.xyzw_from_wxyz(q_wxyz)
    return f'x, y, z, w = ({x:.6f}, {y:.6f}, {z:.6f}, {w:.6f})'


def describe_result(result):
    """One log line for a new estimate."""
    return (f'estimate: {format_quaternion_xyzw(result.quaternion)}, residual '
            f'{result.residual_rms_deg:.3f} deg RMS, uncertainty {result.uncertainty_deg:.3f} '
            f'deg, from {result.samples} samples ({result.inliers} of {result.motions} '
            f'motions used); next: {result.hint}')


class CalibratorNode(Node):
    """The `calibrator` node (module docstring); raises node_config.ConfigError on bad params."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        try:
            self.config = node_config.declare_parameters(self)
        except node_config.ConfigError:
            self.destroy_node()
            raise
        self.session = Session(node_config.session_config(self.config))
        self.stats = StreamStats(LOG_THROTTLE_S)
        self.checks = node_config.check_config(self.config)
        self._rejected_samples = set()
        message_type = PoseStamped if self.config.pose_type == 'pose' else TransformStamped
        self.topics = {   # resolved names (namespace, remapping), for the logs
            stream: self.create_subscription(message_type, stream, callback, qos).topic_name
            for stream, callback, qos in ((LINK, self._on_link, LINK_QOS),
                                          (SENSOR, self._on_sensor, SENSOR_QOS))}
        self.rotation_publisher = self.create_publisher(
            QuaternionStamped, '~/rotation', LATCHED_QOS)
        self.transform_publisher = self.create_publisher(
            TransformStamped, '~/transform', LATCHED_QOS)
        self._tf_broadcaster = None   # tf2_ros.StaticTransformBroadcaster, with publish_tf
        self._tf_problem = None       # why publish_tf has no effect, for /diagnostics
        self._tf_warned = False
        self._start_tf_broadcast()
        self.diagnostics_publisher = self.create_publisher(
            DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        self.create_timer(self.config.diagnostics_period_s, self.publish_diagnostics)
        self.create_service(Trigger, '~/capture', self._on_capture)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save', self._on_save)
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(
            f'calibrating {self.config.setup} rotation {self.config.link_frame} -> '
            f'{self.config.sensor_frame} from {self.resolve_topic_name(LINK)} and '
            f'{self.resolve_topic_name(SENSOR)} ({message_type.__name__}), capture mode '
            f'{self.config.capture_mode}')
        self._move = None          # drift.Move once the samples show a moved marker/sensor
        self._move_checked = 0     # samples the move check has seen
        self._journal_error = None
        try:
            self.journal = None
            self.journal = self._start_journal()
        except node_config.ConfigError:
            self.destroy_node()
            raise

    def now_ns(self):
        """Return the node clock (ROS time; simulated with use_sim_time) in nanoseconds."""
        return self.get_clock().now().nanoseconds

    # --- pose input ------------------------------------------------------------------------

    def _on_link(self, msg):
        self._on_pose(LINK, msg, self.session.add_link_pose)

    def _on_sensor(self, msg):
        self._on_pose(SENSOR, msg, self.session.add_sensor_pose)

    def _on_pose(self, stream, msg, add):
        """
        Check one pose message and feed it to the session, or count and skip it.

        The checks (message_checks module docstring) run cheapest first; a bad message costs
        a counter update, and its text is built only when its throttled log line is due.
        """
        now_ns = self.get_clock().now().nanoseconds
        self.stats.note(stream, now_ns)
        header = msg.header
        try:
            stamp_ns = conversions.stamp_ns_from_header(header)
        except ValueError as error:   # nanosec out of range
            self._bad_message(stream, 'bad_stamp', error)
            return
        reason = message_checks.check(stream, stamp_ns, header.frame_id, now_ns, self.checks)
        if reason is not None:
            checks = self.checks
            self._bad_message(stream, reason, lambda: message_checks.describe(
                reason, stream, stamp_ns, header.frame_id, now_ns, checks))
            return
        try:
            pose = conversions.pose_from_msg(msg)
        except conversions.BadPoseError as error:
            self._bad_message(stream, message_checks.pose_error_reason(error), error)
            return
        events = add(stamp_ns, pose)
        if not events:
            self.stats.note_good(stream, now_ns)
            return
        rejected = [e for e in events if isinstance(e, Rejected) and e.what == stream]
        if rejected:   # out of order or duplicate: the session's verdict on this message
            self._bad_message(stream, message_checks.rejected_reason(rejected[0]),
                              rejected[0].reason)
            events = [e for e in events if not (isinstance(e, Rejected) and e.what == stream)]
        else:
            self.stats.note_good(stream, now_ns)
        self.handle_events(events)

    def _bad_message(self, stream, reason, detail):
        """
        Count a skipped message; log it with the topic and reason, throttled per both.

        detail: the explanation (text, exception, or a function that builds it when logged).
        """
        count = self.stats.note_bad(stream, reason, time.monotonic_ns())
        if count is None:
            return
        total = self.stats.bad[stream, reason]
        so_far = (f'{total} so far' if count == total
                  else f'{count} since the last report, {total} in all')
        text = detail() if callable(detail) else str(detail)
        self.get_logger().warning(
            f'{self.topics[stream]}: bad message skipped ({reason}, {so_far}; reported at most '
            f'every {LOG_THROTTLE_S:g} s): {text}')

    # --- session events --------------------------------------------------------------------

    def handle_events(self, events):
        """
        Journal new samples, publish each new estimate, then log the session's events.

        The journal comes first: a sample is in the file (safe from a crash of the process)
        before the estimate is published, and fsync'd (safe from a power cut) before it is
        reported captured. The log lines come last; then the session is asked for the estimate
        of the new samples, whose events are handled the same way.
        """
        captured = [event for event in events if isinstance(event, SampleCaptured)]
        for event in captured:
            self._write_journal('append', event.sample, sync=False)
        for event in events:
            if isinstance(event, EstimateUpdated):
                self.publish_estimate(event.result)
        if captured:
            self._write_journal('sync')
        for event in events:
            if isinstance(event, SampleCaptured):
                self._log_sample(event)
            elif isinstance(event, EstimateUpdated):
                self.log_estimate(event.result)
            elif isinstance(event, Rejected):
                self._log_rejection(event)
            elif isinstance(event, Notice):
                self.get_logger().info(event.text)
        # The estimate of new samples, if any (the session estimates when asked).
        later = self.session.estimate()
        if later:
            self.handle_events(later)

    def _log_sample(self, event):
        link = event.sample.link
        self.get_logger().info(
            f'sample {event.index} captured at stamp {event.sample.stamp_ns * 1e-9:.3f} s '
            f'(link at [{", ".join(f"{v:.3f}" for v in link.position)}] m)')

    def _log_rejection(self, event):
        text = f'rejected {event.what}: {event.reason}'
        if event.what == 'sample':
            self.get_logger().info(text)
        else:   # per-message rejections can come at the stream rate
            self.get_logger().info(text, throttle_duration_sec=LOG_THROTTLE_S)

    def publish_estimate(self, result):
        """
        Publish `result` on ~/rotation and ~/transform (and, with publish_tf, /tf_static).

        result: anything with `quaternion` and `translation` (a CalibrationResult, Estimate).
        """
        msg = conversions.quaternion_stamped_msg(
            result.quaternion, self.now_ns(), self.config.link_frame)
        self.rotation_publisher.publish(msg)
        transform = self.transform_msg(result, conversions.stamp_ns_from_header(msg.header))
        self.transform_publisher.publish(transform)
        if self.config.publish_tf and self._tf_broadcaster is not None:
            self._tf_broadcaster.sendTransform(transform)

    def log_estimate(self, result):
        """Log a new estimate, its rejected samples and warnings; check for a moved marker."""
        self.get_logger().info(describe_result(result))
        self._log_rejected_samples(result)
        for warning in result.warnings:
            self.get_logger().warning(warning, throttle_duration_sec=LOG_THROTTLE_S)
        self._check_move(result)

    def transform_msg(self, result, stamp_ns):
        """Return the TransformStamped link_frame -> sensor_frame of `result`."""
        return conversions.transform_stamped_msg(
            Pose.create(result.translation, result.quaternion), stamp_ns,
            self.config.link_frame, self.config.sensor_frame)

    def _start_tf_broadcast(self):
        """
        With publish_tf, make the /tf_static broadcaster (once), or say why there is none.

        tf2_ros comes with a ROS 2 install, not with the PyPI wheels: without it the node
        warns once and /diagnostics keeps saying so (the result is still on ~/transform).
        """
        if not self.config.publish_tf or self._tf_broadcaster is not None:
            return
        try:
            import tf2_ros
        except ImportError:
            self._tf_problem = TF2_ROS_MISSING
            if not self._tf_warned:
                self._tf_warned = True
                self.get_logger().warning(TF2_ROS_MISSING)
            return
        self._tf_problem = None
        self._tf_broadcaster = tf2_ros.StaticTransformBroadcaster(self)
        result = self.session.result
        if result is not None:   # publish_tf turned on at runtime: send the current estimate
            self._tf_broadcaster.sendTransform(self.transform_msg(result, self.now_ns()))

    def _log_rejected_samples(self, result):
        """Log each sample the estimator newly rejects (bad detections), with the reason."""
        rejected = {entry['sample']: entry['reason'] for entry in result.rejected
                    if 'sample' in entry}
        for index in sorted(set(rejected) - self._rejected_samples):
            self.get_logger().info(f'rejected sample {index}: {rejected[index]}')
        self._rejected_samples = set(rejected)

    def _check_move(self, result):
        """Warn (once, until ~/reset) when the newest samples show a moved marker or sensor."""
        samples = self.session.samples
        if self._move is None:
            options = self.session.config.calibration
            self._move = drift.find_move(
                samples, result.quaternion, options.setup, options.invert_sensor,
                first=max(0, self._move_checked - drift.RECENT + 1))
            if self._move is not None:
                self.get_logger().warning(self._move.text())
        self._move_checked = len(samples)

    def move_warning(self):
        """Return the moved-marker warning with the current sample count, or None."""
        if self._move is None:
            return None
        return replace(self._move, samples=len(self.session.samples) - self._move.first).text()

    # --- samples journal -------------------------------------------------------------------

    def _journal_header(self):
        return journal.JournalHeader(self.config.setup, self.config.link_frame,
                                     self.config.sensor_frame)

    def _start_journal(self):
        """
        Open samples_file; with resume:=true, reload its samples and publish the estimate.

        :raises node_config.ConfigError: when the journal cannot be used (in use by another
            node, recorded with another setup or frames while resume:=true, not writable).
        """
        try:
            opened, report = journal.start(self.config.samples_file, self._journal_header(),
                                           self.config.resume)
        except (journal.JournalRefused, OSError) as error:
            raise node_config.ConfigError(
                f'samples_file {self.config.samples_file}: {error}') from None
        logger = self.get_logger()
        for level, text in report.messages:   # one call site per severity (rclpy insists)
            if level == 'error':
                logger.error(text)
            elif level == 'warning':
                logger.warning(text)
            else:
                logger.info(text)
        if report.samples:
            # Already in the journal: not appended again, not logged one by one.
            events = self.session.add_samples(report.samples)
            self.handle_events([e for e in events if not isinstance(e, SampleCaptured)])
            if self.session.result is None:
                self.get_logger().info(f'no estimate from the resumed samples yet: '
                                       f'{self.session.last_error}')
        return opened

    def _write_journal(self, method, *args, **kwargs):
        """Call the samples_file Journal's `method`; a failure is kept in view."""
        if self.journal is None:
            return
        try:
            getattr(self.journal, method)(*args, **kwargs)
            self._journal_error = None
        except OSError as error:
            reason = error.strerror or error
            if self.journal.unwritten:
                self._journal_error = (
                    f'{self.journal.unwritten} captured samples not yet saved to '
                    f'{self.journal.path} ({reason}): they are kept and written with the next '
                    'sample')
            else:
                self._journal_error = (
                    f'could not fsync {self.journal.path} ({reason}): the samples are in the '
                    'file but may not survive a power cut; tried again with the next sample')
            self.get_logger().error(self._journal_error)

    def _restart_journal(self):
        """Start a new journal (~/reset); return what happened to the old one, as text."""
        if self.journal is None:
            return ''
        try:
            moved = self.journal.restart()
        except OSError as error:
            self._journal_error = f'could not start a new samples journal: {error}'
            self.get_logger().error(self._journal_error)
            return f'; {self._journal_error}'
        self._journal_error = None
        return f'; the old samples journal was moved to {moved}' if moved else ''

    def _update_journal_header(self):
        """Record a runtime change of setup or frames in the journal's first line."""
        if self.journal is None:
            return
        try:
            self.journal.set_header(self._journal_header())
        except OSError as error:
            self.get_logger().error(f'could not record the new setup or frames in '
                                    f'{self.journal.path}: {error}')

    def destroy_node(self):
        """Close the samples journal (releasing its lock), then destroy the node."""
        if getattr(self, 'journal', None) is not None:
            self.journal.close()
            self.journal = None
        return super().destroy_node()

    # --- diagnostics -----------------------------------------------------------------------

    def status_message(self):
        """Describe the state in operator words."""
        result = self.session.result
        if result is not None:
            return f'estimating: uncertainty {result.uncertainty_deg:.2g} deg'
        if self.session.state == 'waiting for poses':
            missing = [s for s in (LINK, SENSOR) if not self.stats.received[s]]
            if missing:
                return f'waiting for poses (nothing on {" and ".join(missing)} yet)'
            if self.stats.bad_total:
                (stream, reason), _ = self.stats.bad.most_common(1)[0]
                return (f'waiting for poses ({self.stats.bad_total} bad messages skipped, '
                        f'most for {reason} on {stream})')
            return 'waiting for poses (none paired yet: are both stamped on the same clock?)'
        return (f'collecting: {len(self.session.samples)} samples, need motions about 2 '
                'different axes')

    def diagnostic_status(self):
        """Build the DiagnosticStatus published on /diagnostics."""
        result = self.session.result
        counters = self.session.counters
        stale = self.stats.stale_reasons(self.now_ns(), STALE_AFTER_S)
        problems = [text for _, text in stale]
        if result is not None and result.residual_rms_deg > HIGH_RESIDUAL_DEG:
            problems.append(f'high residual {result.residual_rms_deg:.2f} deg RMS: check the '
                            'frame conventions and the time alignment of the streams')
        if result is not None:
            problems += list(result.warnings)
        problems += [text for text in (self.move_warning(), self._journal_error) if text]
        if self.config.publish_tf and self._tf_problem:
            problems.append(self._tf_problem)
        message = '; '.join([self.status_message()] + problems)
        hint = result.hint if result is not None else self.session.last_error
        values = {
            'state': self.session.state,
            'samples': counters['samples'],
            'motions': result.motions if result is not None else counters['motions'],
            'inliers': result.inliers if result is not None else 0,
            'residual_rms_deg': _number_text(result and result.residual_rms_deg),
            'uncertainty_deg': _number_text(result and result.uncertainty_deg),
            'method': result.method if result is not None else '',
            'translation_xyz_m': (' '.join(f'{v:.6f}' for v in result.translation)
                                  if result is not None else ''),
            'translation_uncertainty_mm': _number_text(
                result and result.translation_uncertainty_mm),
            'tf_static': self._tf_status(),
            'hint': hint,
            'link_messages': self.stats.received[LINK],
            'sensor_messages': self.stats.received[SENSOR],
            'bad_messages': self.stats.bad_total,
            'stale': ' '.join(stream for stream, _ in stale),
            'paired_poses': counters['pairs'],
            'rejected_messages': counters['rejected'],
            # Clock jumps back (a bag played again): each restarted the pairing; stills that
            # repeat earlier samples after one are not added twice.
            'time_jumps': counters['time_jumps'],
            'repeated_samples': counters['repeated_samples'],
        }
        for (stream, reason), count in sorted(self.stats.bad.items()):
            values[message_checks.diagnostic_key(stream, reason)] = count
        return DiagnosticStatus(
            level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK,
            name=DIAGNOSTIC_NAME, message=message, hardware_id=self.config.link_frame,
            values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

    def _tf_status(self):
        """Return the /tf_static broadcast state, for /diagnostics."""
        if not self.config.publish_tf:
            return 'off (publish_tf is false)'
        if self._tf_problem:
            return 'not broadcast: tf2_ros is not installed'
        return 'broadcast'

    def publish_diagnostics(self):
        """Publish the status once (the timer's callback)."""
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
        self._move, self._move_checked = None, 0
        journal_text = self._restart_journal()
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
        try:
            path = persistence.write_result_yaml(
                self.config.result_file, result, self.config.link_frame,
                self.config.sensor_frame, setup=self.config.setup)
        except OSError as error:
            response.success = False
            response.message = f'could not write {self.config.result_file}: {error}'
            self.get_logger().error(response.message)
            return response
        response.success = True
        response.message = f'saved to {path}'
        self.get_logger().info(f'result {response.message}')
        self._save_easy_handeye2(result, response)
        self.get_logger().info(
            'to broadcast the result on /tf_static: ' + exports.static_transform_publisher_command(
                result, self.config.link_frame, self.config.sensor_frame))
        return response

    def _save_easy_handeye2(self, result, response):
        """Write easy_handeye2_file (when set) beside the result file; note it in `response`."""
        target = self.config.easy_handeye2_file
        if not target:
            return
        # The link poses' header frame is the robot base (eye_in_hand); '' when not checked.
        base = {'robot_base_frame': self.config.link_frame_id} \
            if self.config.setup == 'eye_in_hand' else {}
        try:
            path = persistence.atomic_write_text(target, exports.easy_handeye2_yaml(
                result, self.config.link_frame, self.config.sensor_frame,
                setup=self.config.setup, name=exports.easy_handeye2_name(target), **base))
        except OSError as error:
            response.success = False
            response.message += f'; could not write easy_handeye2_file {target}: {error}'
            self.get_logger().error(f'could not write easy_handeye2_file {target}: {error}')
            return
        response.message += f'; easy_handeye2 layout saved to {path}'
        self.get_logger().info(f'result in the easy_handeye2 layout saved to {path}')

    # --- parameters at runtime -------------------------------------------------------------

    def _check_parameters(self, parameters):
        try:
            node_config.updated(self.config, parameters)
        except node_config.ConfigError as error:
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters):
        new = node_config.updated(self.config, parameters)
        old, self.config = self.config, new
        self.checks = node_config.check_config(new)
        changed = [n for n, v in new.as_dict().items() if old.as_dict()[n] != v]
        if changed:
            self.get_logger().info(f'parameters changed: {", ".join(changed)}')
        if set(changed) & set(journal.HEADER_KEYS):
            self._update_journal_header()
        if 'publish_tf' in changed:
            self._start_tf_broadcast()
        if any(name not in PRESENTATION_PARAMETERS for name in changed):
            self._rebuild_session()

    def _rebuild_session(self):
        """Start a session with the new settings and re-estimate from the samples so far."""
        samples = self.session.samples
        self.session = Session(node_config.session_config(self.config))
        if samples:
            self.get_logger().info(
                f're-estimating from the {len(samples)} samples with the new settings')
            events = self.session.add_samples(samples)
            self.handle_events([e for e in events if not isinstance(e, SampleCaptured)])


def _number_text(value):
    if value is None or value is False:
        return ''
    return f'{float(value):.6g}' if np.isfinite(value) else 'nan'


def _install_stop_handlers():
    """
    SIGINT and SIGTERM end the node cleanly: rclpy shuts down, spin returns, exit status 0.

    No KeyboardInterrupt is raised: one raised while rclpy converts a message in C++ comes out
    as a RuntimeError from take_message (seen once in CI), not as KeyboardInterrupt. rclpy's
    own handlers (installed by rclpy.init after these, and chaining to them) wake the
    executor; these also cover a signal that comes before rclpy.init. Returns the list that
    records the signals received.
    """
    received = []

    def on_signal(signum, frame):
        received.append(signum)
        try:
            rclpy.try_shutdown()
        except RuntimeError:   # RCLError: rclpy's own handler shut the context down meanwhile
            pass
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, on_signal)
    return received


def _start_node():
    """Make the executor and the node; (None, None) when a signal stopped rclpy meanwhile."""
    try:
        return SingleThreadedExecutor(), CalibratorNode()
    except node_config.ConfigError:
        raise
    except KeyboardInterrupt:
        rclpy.try_shutdown()
        return None, None
    except Exception:
        if rclpy.ok():
            raise
        return None, None


def main(args=None):
    """Run the calibrator node; return 2 (after logging the reason) for invalid parameters."""
    terminated = _install_stop_handlers()
    rclpy.init(args=args)
    if terminated:
        rclpy.try_shutdown()
    try:
        executor, node = _start_node()
    except node_config.ConfigError as error:
        rclpy.logging.get_logger(NODE_NAME).fatal(f'invalid parameters: {error}')
        rclpy.try_shutdown()
        return 2
    if node is None:
        return None
    # Everything made so far (modules, the resumed session) lives as long as the process:
    # keep it out of the cyclic collector, whose full passes over it took ~0.1 s and could
    # land on the callback that completes a sample.
    gc.freeze()
    try:
        _spin(node, executor)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return None


def _spin(node, executor):
    """
    Spin until rclpy shuts down (a stop signal, _install_stop_handlers).

    An explicit executor: rclpy.spin's global one cannot be made once a signal has shut the
    context down. A signal that shuts it down between two executor steps makes the next step
    fail with RCLError ('the given context is not valid', seen once in CI) instead of
    ExternalShutdownException: with the context down, that is the same stop.
    """
    try:
        rclpy.spin(node, executor=executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:   # RCLError
        if rclpy.ok():
            raise


if __name__ == '__main__':
    raise SystemExit(main())
