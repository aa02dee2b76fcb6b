"""
The live calibrator node: pose topics in, hand-eye rotation estimate out (DESIGN.md contract 4).

A thin shell around session.Session:
- subscribes `link_pose` and `sensor_pose` (relative names; PoseStamped, or TransformStamped
  with pose_type:=transform) and feeds the header stamps and poses to the session;
- publishes `~/rotation` (QuaternionStamped, reliable + transient local, depth 1, frame_id =
  link_frame) on each new estimate and a status on `/diagnostics` at diagnostics_period_s;
- serves `~/capture`, `~/reset` and `~/save` (std_srvs/Trigger).

Messages are read only through conversions; quaternions in the core are (w, x, y, z).
Times come from header stamps and the node clock (so use_sim_time and bag replays work).
"""

from collections import Counter
import signal

from diagnostic_msgs.msg import DiagnosticArray
from diagnostic_msgs.msg import DiagnosticStatus
from diagnostic_msgs.msg import KeyValue
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import QuaternionStamped
from geometry_msgs.msg import TransformStamped
import numpy as np
from quatcal_ros import conversions
from quatcal_ros import node_config
from quatcal_ros import persistence
from quatcal_ros import quaternion as quat
from quatcal_ros.session import EstimateUpdated
from quatcal_ros.session import Notice
from quatcal_ros.session import Rejected
from quatcal_ros.session import SampleCaptured
from quatcal_ros.session import Session
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from rclpy.qos import HistoryPolicy
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from std_srvs.srv import Trigger

NODE_NAME = 'calibrator'
DIAGNOSTIC_NAME = 'calibrator: hand-eye rotation'
LINK, SENSOR = 'link_pose', 'sensor_pose'
# A stream that has sent nothing for this long (node clock) is stale: diagnostics say WARN.
STALE_AFTER_S = 3.0
# An RMS motion residual above this (degrees) means inconsistent data: diagnostics say WARN.
HIGH_RESIDUAL_DEG = 1.0
LOG_THROTTLE_S = 5.0
# Parameters that change only the presentation, not the session.
PRESENTATION_PARAMETERS = ('link_frame', 'sensor_frame', 'result_file')

LINK_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)
# BEST_EFFORT matches reliable and best-effort (sensor data) publishers alike.
SENSOR_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
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


class StreamStats:
    """Messages received per stream, bad ones per stream and field, and when last heard."""

    def __init__(self):
        self.received = Counter()
        self.bad = Counter()
        self.first_ns = None
        self.last_ns = {}

    def note(self, stream, now_ns):
        self.received[stream] += 1
        self.last_ns[stream] = now_ns
        if self.first_ns is None:
            self.first_ns = now_ns

    def note_bad(self, stream, field):
        self.bad[stream, field or 'message'] += 1

    @property
    def bad_total(self):
        return sum(self.bad.values())

    def stale(self, now_ns, after_s=STALE_AFTER_S):
        """Streams not heard for after_s (node clock) since the first message of either."""
        if self.first_ns is None:
            return []
        limit = now_ns - int(after_s * 1e9)
        return [stream for stream in (LINK, SENSOR)
                if self.last_ns.get(stream, self.first_ns) < limit]


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
        self.stats = StreamStats()
        self._rejected_samples = set()
        message_type = PoseStamped if self.config.pose_type == 'pose' else TransformStamped
        self.create_subscription(message_type, LINK, self._on_link, LINK_QOS)
        self.create_subscription(message_type, SENSOR, self._on_sensor, SENSOR_QOS)
        self.rotation_publisher = self.create_publisher(
            QuaternionStamped, '~/rotation', LATCHED_QOS)
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

    def now_ns(self):
        """Return the node clock (ROS time; simulated with use_sim_time) in nanoseconds."""
        return self.get_clock().now().nanoseconds

    # --- pose input ------------------------------------------------------------------------

    def _on_link(self, msg):
        self._on_pose(LINK, msg, self.session.add_link_pose)

    def _on_sensor(self, msg):
        self._on_pose(SENSOR, msg, self.session.add_sensor_pose)

    def _on_pose(self, stream, msg, add):
        self.stats.note(stream, self.now_ns())
        try:
            pose = conversions.pose_from_msg(msg)
            stamp_ns = conversions.stamp_ns_from_header(msg.header)
        except conversions.BadPoseError as error:
            self._bad_message(stream, getattr(error, 'field', ''), str(error))
            return
        except ValueError as error:   # a stamp out of range
            self._bad_message(stream, 'header.stamp', str(error))
            return
        self.handle_events(add(stamp_ns, pose))

    def _bad_message(self, stream, field, reason):
        self.stats.note_bad(stream, field)
        count = self.stats.bad[stream, field or 'message']
        self.get_logger().warning(
            f'{stream}: bad message ignored ({count} so far with bad {field or "content"}): '
            f'{reason}', throttle_duration_sec=LOG_THROTTLE_S)

    # --- session events --------------------------------------------------------------------

    def handle_events(self, events):
        """Log the session's events and publish each new estimate."""
        for event in events:
            if isinstance(event, SampleCaptured):
                self._log_sample(event)
            elif isinstance(event, EstimateUpdated):
                self.publish_estimate(event.result)
            elif isinstance(event, Rejected):
                self._log_rejection(event)
            elif isinstance(event, Notice):
                self.get_logger().info(event.text)

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
        """Publish `result` on ~/rotation and log it."""
        msg = conversions.quaternion_stamped_msg(
            result.quaternion, self.now_ns(), self.config.link_frame)
        self.rotation_publisher.publish(msg)
        self.get_logger().info(describe_result(result))
        self._log_rejected_samples(result)
        for warning in result.warnings:
            self.get_logger().warning(warning, throttle_duration_sec=LOG_THROTTLE_S)

    def _log_rejected_samples(self, result):
        """Log each sample the estimator newly rejects (bad detections), with the reason."""
        rejected = {entry['sample']: entry['reason'] for entry in result.rejected
                    if 'sample' in entry}
        for index in sorted(set(rejected) - self._rejected_samples):
            self.get_logger().info(f'rejected sample {index}: {rejected[index]}')
        self._rejected_samples = set(rejected)

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
                return f'waiting for poses ({self.stats.bad_total} bad messages ignored)'
            return 'waiting for poses (none paired yet: are both stamped on the same clock?)'
        return (f'collecting: {len(self.session.samples)} samples, need motions about 2 '
                'different axes')

    def diagnostic_status(self):
        """Build the DiagnosticStatus published on /diagnostics."""
        result = self.session.result
        counters = self.session.counters
        problems = [f'no message on {stream} for over {STALE_AFTER_S:g} s'
                    for stream in self.stats.stale(self.now_ns())]
        if result is not None and result.residual_rms_deg > HIGH_RESIDUAL_DEG:
            problems.append(f'high residual {result.residual_rms_deg:.2f} deg RMS: check the '
                            'frame conventions and the time alignment of the streams')
        if result is not None:
            problems += list(result.warnings)
        message = '; '.join([self.status_message()] + problems)
        hint = result.hint if result is not None else self.session.last_error
        values = {
            'state': self.session.state,
            'samples': counters['samples'],
            'motions': result.motions if result is not None else counters['motions'],
            'inliers': result.inliers if result is not None else 0,
            'residual_rms_deg': _number_text(result and result.residual_rms_deg),
            'uncertainty_deg': _number_text(result and result.uncertainty_deg),
            'hint': hint,
            'link_messages': self.stats.received[LINK],
            'sensor_messages': self.stats.received[SENSOR],
            'bad_messages': self.stats.bad_total,
            'paired_poses': counters['pairs'],
            'rejected_messages': counters['rejected'],
        }
        for (stream, field), count in sorted(self.stats.bad.items()):
            values[f'bad {stream} {field}'] = count
        return DiagnosticStatus(
            level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK,
            name=DIAGNOSTIC_NAME, message=message, hardware_id=self.config.link_frame,
            values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

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
        response.success = True
        response.message = (f'session cleared: {discarded} samples discarded (the last '
                            '~/rotation stays latched until a new estimate)')
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
        return response

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
        changed = [n for n, v in new.as_dict().items() if old.as_dict()[n] != v]
        if changed:
            self.get_logger().info(f'parameters changed: {", ".join(changed)}')
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


def _install_sigterm_handler():
    """
    SIGTERM ends the node like Ctrl-C: rclpy shuts down, spin returns, exit status 0.

    rclpy's own handler (installed by rclpy.init after this one, and chaining to it) wakes
    the executor; this one also covers a SIGTERM that comes before rclpy.init. Returns the
    list that records the signals received.
    """
    received = []

    def on_sigterm(signum, frame):
        received.append(signum)
        rclpy.try_shutdown()
    signal.signal(signal.SIGTERM, on_sigterm)
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
    terminated = _install_sigterm_handler()
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
    try:
        # An explicit executor: rclpy.spin's global one cannot be made once a signal has
        # shut the context down.
        rclpy.spin(node, executor=executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return None


if __name__ == '__main__':
    raise SystemExit(main())
