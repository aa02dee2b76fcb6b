"""
Tests of the calibrator node over real DDS: in-process (rclpy style) and as processes.

In-process tests build the node in a private Context with parameter_overrides and drive it
from a second node through the middleware, spinning one executor with deadlines.  The
multi-process test runs `python -m quatcal_ros sim_cell` and `... calibrator` and stops them
with SIGINT / SIGTERM.  Two domain ids reserved on this host (conftest: domain_id for the
in-process tests, process_domain_id for the processes) keep them apart from everything else.
"""

import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time
import types

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import PoseWithCovarianceStamped
from geometry_msgs.msg import TransformStamped
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.ros import conversions
from quatcal_ros.ros import inputs
from quatcal_ros.ros.diagnostics import DIAGNOSTIC_NAME
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.sim import simulation
from quatcal_ros.stream.settings import ConfigError
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from rclpy.serialization import deserialize_message
from ros_harness import harnesses_of
from ros_harness import LATCHED
from ros_harness import logged_warnings
from ros_harness import ProcessWatcher
from ros_harness import SpinMixin
from ros_harness import stop_process
from std_srvs.srv import Trigger
import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]
NS = NS_PER_S
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def angle_deg(q_wxyz, p_wxyz):
    """Angle between two rotations (w, x, y, z), degrees."""
    return float(np.degrees(quat.angle_between(q_wxyz, p_wxyz)))


def rotation_of(msg):
    """(w, x, y, z) of a QuaternionStamped."""
    q = msg.quaternion
    return np.array([q.w, q.x, q.y, q.z])


class Harness(SpinMixin):
    """A calibrator node and a driver node in one private context and executor."""

    def __init__(self, domain_id, overrides=(), sensor_qos=RELIABLE, message_type=PoseStamped,
                 sensor_type=None):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        # The simulated streams are stamped in 2023 (simulation.DEFAULT_START_NS): the check
        # of stamps against the node clock is off unless a test sets it.
        overrides = [Parameter('max_stamp_offset_s', value=0.0), *overrides]
        self.node = CalibratorNode(context=self.context, parameter_overrides=list(overrides))
        self.driver = rclpy.create_node('test_driver', context=self.context)
        self.message_types = {'link_pose': message_type,
                              'sensor_pose': sensor_type or message_type}
        self.link_pub = self.driver.create_publisher(message_type, 'link_pose', RELIABLE)
        self.sensor_pub = self.driver.create_publisher(self.message_types['sensor_pose'],
                                                       'sensor_pose', sensor_qos)
        self.watch_outputs()
        self.clients = {name: self.driver.create_client(Trigger, f'/calibrator/{name}')
                        for name in ('capture', 'reset', 'save')}
        self.sent = {'link_pose': 0, 'sensor_pose': 0}
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(lambda: self.link_pub.get_subscription_count()
                        and self.sensor_pub.get_subscription_count()
                        and all(c.service_is_ready() for c in self.clients.values()),
                        what='discovery of the calibrator')

    def call(self, name):
        future = self.clients[name].call_async(Trigger.Request())
        self.spin_until(future.done, what=f'the {name} service')
        return future.result()

    # The frames of each stream's messages (header, a transform's child): those the node's
    # defaults expect.
    FRAMES = {'link_pose': ('base_link', 'tool0'), 'sensor_pose': ('camera', 'marker')}

    def publish(self, stream, stamp_ns, pose):
        publisher = self.link_pub if stream == 'link_pose' else self.sensor_pub
        message_type = self.message_types[stream]
        frame, child = self.FRAMES[stream]
        if message_type is PoseStamped:
            msg = conversions.pose_stamped_msg(pose, stamp_ns, frame)
        elif message_type is PoseWithCovarianceStamped:
            msg = conversions.pose_with_covariance_stamped_msg(pose, stamp_ns, frame)
        else:
            msg = conversions.transform_stamped_msg(pose, stamp_ns, frame, child)
        publisher.publish(msg)
        self.sent[stream] += 1

    def wait_received(self, best_effort_slack=0, timeout=10.0):
        """Spin until the node has the messages sent (best-effort ones may be dropped)."""
        received = self.node.stats.received

        def done():
            return (received['link_pose'] >= self.sent['link_pose']
                    and received['sensor_pose'] >= self.sent['sensor_pose'] - best_effort_slack)
        try:
            self.spin_until(done, timeout, what='the node to receive the poses')
        except AssertionError:
            # Best-effort sensor poses beyond the slack may be lost; nothing else may be.
            if received['link_pose'] < self.sent['link_pose'] or not best_effort_slack:
                raise

    def publish_events(self, events, chunk=60, best_effort_slack=0):
        """Publish (stream, stamp_ns, pose) in order, in chunks the node keeps up with."""
        for start in range(0, len(events), chunk):
            for stream, stamp_ns, pose in events[start:start + chunk]:
                self.publish(stream, stamp_ns, pose)
            self.wait_received(best_effort_slack)


@pytest.fixture
def harness_factory(domain_id):
    yield from harnesses_of(Harness, domain_id)


def still_events(cell, link, start_ns, duration_s=0.8, rate_hz=25.0):
    """Both streams at rate_hz holding one link pose (noise-free sensor)."""
    sensor = cell.sensor_pose(link)
    events = []
    for i in range(int(duration_s * rate_hz)):
        stamp = start_ns + int(i * NS / rate_hz)
        events += [('link_pose', stamp, link), ('sensor_pose', stamp, sensor)]
    return events


def turned(cell, axis, angle_deg_, shift=(0.0, 0.0, 0.0)):
    """Home link pose turned about a base-frame axis and shifted."""
    q = quat.multiply(quat.from_axis_angle(axis, np.radians(angle_deg_)), cell.home.quaternion)
    return Pose(cell.home.position + np.asarray(shift), quat.normalize(q))


# --- recovery from a simulated stop-and-go cell ---------------------------------------------

def stream_events(streams):
    """Merge the streams in delivery order, as (topic, header stamp, pose)."""
    events = [(stamp, 0, 'link_pose', stamp, pose) for stamp, pose in streams.link]
    events += [(delivery, 1, 'sensor_pose', stamp, pose) for delivery, (stamp, pose)
               in zip(streams.sensor_delivery_ns, streams.sensor)]
    return [event[2:] for event in sorted(events, key=lambda e: e[:2])]


def test_recovers_the_rotation_of_a_simulated_cell(harness_factory):
    rng = np.random.default_rng(5)
    cell = simulation.random_cell(rng)
    streams = simulation.stop_and_go_streams(
        rng, cell, n_stops=12, link_rate_hz=50.0, sensor_rate_hz=30.0, still_s=1.0, move_s=1.0,
        rotation_noise_deg=0.2, translation_noise_m=0.001, rotation_spread_deg=40.0)
    # The sensor publishes with sensor-data QoS (best effort), as camera drivers do.
    h = harness_factory(sensor_qos=qos_profile_sensor_data)
    h.publish_events(stream_events(streams), best_effort_slack=20)
    h.spin_until(lambda: h.rotations, what='an estimate on ~/rotation')
    result = h.node.session.result
    assert result.samples >= 10
    assert 0.0 < result.uncertainty_deg < 0.5
    error = angle_deg(result.quaternion, cell.mounting.quaternion)
    assert error < 3.0 * result.uncertainty_deg
    h.spin_until(lambda: len(h.rotations) and np.allclose(
        rotation_of(h.rotations[-1]) * np.sign(rotation_of(h.rotations[-1])[0]),
        result.quaternion, atol=1e-6), what='the last estimate on ~/rotation')
    assert h.rotations[-1].header.frame_id == 'tool0'


# --- what the motions must be ---------------------------------------------------------------

def test_estimate_needs_two_non_parallel_motions_then_save_and_reset(harness_factory, tmp_path):
    rng = np.random.default_rng(2)
    cell = simulation.random_cell(rng)
    result_file = tmp_path / 'out' / 'calibration.yaml'
    h = harness_factory([Parameter('result_file', value=str(result_file)),
                         Parameter('diagnostics_period_s', value=0.2)])
    z = [0.0, 0.0, 1.0]
    stops = [turned(cell, z, 0.0), turned(cell, z, 30.0, (0.05, 0.0, 0.0)),
             turned(cell, z, -25.0, (0.0, 0.05, 0.02)), turned(cell, z, 60.0, (0.0, 0.0, 0.04))]
    start = simulation.DEFAULT_START_NS
    for k, link in enumerate(stops[:2]):
        h.publish_events(still_events(cell, link, start + k * NS))
        h.spin_until(lambda: len(h.node.session.samples) == k + 1, what=f'sample {k}')
    h.spin_for(0.3)
    assert h.node.session.result is None and h.rotations == []
    refused = h.call('save')
    assert not refused.success and 'no estimate' in refused.message
    assert not result_file.exists()
    status = h.node.diagnostic_status()
    assert status.message.startswith('collecting: 2 sample(s)')

    # Motions about one axis only (as a SCARA's): the translations fix the rotation, and the
    # offset along the axis is named, loudly, as what the data do not determine.
    for k, link in enumerate(stops[2:], 2):
        h.publish_events(still_events(cell, link, start + k * NS))
        h.spin_until(lambda: len(h.node.session.samples) == k + 1, what=f'sample {k}')
    h.spin_until(lambda: h.node.session.result is not None
                 and h.node.session.result.samples == 4, what='the estimate of 4 samples')
    result = h.node.session.result
    (unobservable,) = result.unobservable
    assert unobservable['what'] == 'translation'
    assert angle_deg(result.quaternion, cell.mounting.quaternion) < 1e-3   # noise-free
    status = h.node.diagnostic_status()
    assert status.level == DiagnosticStatus.WARN and 'one axis only' in status.message

    # A motion about another axis determines everything.
    tilted = turned(cell, [1.0, 0.0, 0.0], 30.0, (0.0, -0.05, 0.0))
    h.publish_events(still_events(cell, tilted, start + 4 * NS))
    h.spin_until(lambda: h.rotations, what='an estimate after a non-parallel motion')
    h.spin_until(lambda: h.node.session.result.samples == 5, what='the estimate of 5 samples')
    result = h.node.session.result
    assert result.unobservable == []
    assert angle_deg(result.quaternion, cell.mounting.quaternion) < 1e-3
    assert angle_deg(rotation_of(h.rotations[-1]), cell.mounting.quaternion) < 1e-3

    h.diagnostics.clear()
    h.spin_until(lambda: any(s.name == DIAGNOSTIC_NAME and s.message.startswith('estimating')
                             for a in h.diagnostics for s in a.status),
                 what='diagnostics of the estimate')
    status = [s for a in h.diagnostics for s in a.status][-1]
    values = {kv.key: kv.value for kv in status.values}
    assert status.hardware_id == 'tool0'
    assert values['state'] == 'estimating' and values['samples'] == '5'
    assert float(values['uncertainty_deg']) < 0.01
    for key in ('motions', 'inliers', 'residual_rms_deg', 'hint', 'link_messages',
                'sensor_messages', 'bad_messages', 'sensor_jumps'):
        assert key in values

    # A runtime change re-estimates from the same samples and publishes again.
    published = len(h.rotations)
    (changed,) = h.node.set_parameters([Parameter('robust', value=False)])
    assert changed.successful
    h.spin_until(lambda: len(h.rotations) > published, what='a re-estimate on ~/rotation')
    assert len(h.node.session.samples) == 5
    assert h.node.session.config.calibration.robust is False
    assert angle_deg(h.node.session.result.quaternion, cell.mounting.quaternion) < 1e-3
    # A new sensor time offset re-estimates too, but the samples keep their pairing: it said
    # nothing, and a residual that stayed high looked like the offset had not helped.
    with logged_warnings(h.node) as warned:
        (changed,) = h.node.set_parameters([Parameter('sensor_time_offset_s', value=0.0)])
        assert changed.successful and not warned   # unchanged: nothing to say
        (changed,) = h.node.set_parameters([Parameter('sensor_time_offset_s', value=0.03)])
        assert changed.successful
    assert warned == ['sensor_time_offset_s applies to the poses from now on: the 5 samples '
                      'taken keep the pairing they were taken with; call ~/reset to take them '
                      'again with the new offset']
    # The journal lists the offsets its samples were paired with: 0.03 joins with the first
    # sample paired with it (test_resume.py), not when set.
    assert h.node.journal.header.sensor_time_offsets == (0.0,)
    # How samples are taken does not change how those taken are solved: no re-estimate.
    session, estimate = h.node.session, h.node.session.result
    changed = h.node.set_parameters_atomically([Parameter('still_window_s', value=0.8),
                                                Parameter('capture_mode', value='manual')])
    assert changed.successful and h.node.session is session
    assert session.result is estimate and session.estimate() == []   # nothing to publish
    assert session.config.capture.window_ns == 800_000_000
    assert session.config.capture.mode == 'manual' and len(session.samples) == 5

    saved = h.call('save')
    assert saved.success and str(result_file) in saved.message
    document = yaml.safe_load(result_file.read_text())
    q_xyzw = [document['rotation'][k] for k in 'xyzw']
    assert angle_deg(quat.wxyz_from_xyzw(q_xyzw), cell.mounting.quaternion) < 1e-3
    assert document['parent_frame'] == 'tool0' and document['child_frame'] == 'camera'
    assert document['quality']['samples'] == 5

    reset = h.call('reset')
    assert reset.success and '5 samples' in reset.message
    assert h.node.session.samples == [] and h.node.session.result is None
    assert not h.call('save').success
    assert h.node.journal.header.sensor_time_offsets == (0.03,)   # the new journal's


# --- services in manual mode ----------------------------------------------------------------

def test_manual_capture_service(harness_factory):
    rng = np.random.default_rng(3)
    cell = simulation.random_cell(rng)
    h = harness_factory([Parameter('capture_mode', value='manual'),
                         Parameter('still_window_s', value=0.2)])
    refused = h.call('capture')
    assert not refused.success and 'no paired poses' in refused.message
    assert 'so far' not in refused.message
    # Sensor poses that all fail a check (a detector with the wrong units): the refusal said
    # to check the clocks; it says what was skipped too.
    now = h.node.now_ns()
    h.publish_events([('sensor_pose', now - k * 25 * NS // 1000, Pose.create(
        [0.0, 0.0, 2e6], [1.0, 0.0, 0.0, 0.0])) for k in range(8, 0, -1)])
    refused = h.call('capture')
    assert not refused.success and ('(so far 8 bad messages skipped, most for '
                                    'implausible_position on sensor_pose, the first: position '
                                    '[0.0, 0.0, 2000000.0] m is farther than') in refused.message
    # ~/reset starts the count over: what was skipped before it is not this session's.
    assert h.call('reset').success
    said = []   # the node's log lines from here
    h.node.log.logger = types.SimpleNamespace(info=said.append, warning=said.append)
    refused = h.call('capture')
    assert not refused.success and 'so far' not in refused.message
    assert h.node.stats.bad_total == 8   # (/diagnostics keeps counting since the start)
    # Asked again at once (a client polling until the robot is still): answered, logged once.
    assert h.call('capture').message == refused.message
    assert said == [f'capture refused: {refused.message}']

    def publish_still(link):
        now = h.node.now_ns()
        h.publish_events(still_events(cell, link, now - int(0.5 * NS), duration_s=0.5,
                                      rate_hz=40.0))

    publish_still(cell.home)
    assert h.node.session.samples == []        # manual mode: nothing captured by itself
    captured = h.call('capture')
    assert captured.success, captured.message
    assert len(h.node.session.samples) == 1
    again = h.call('capture')
    assert not again.success and 'no motion' in again.message
    h.spin_for(0.6)     # so that the next stamps follow the last ones
    publish_still(turned(cell, [0.0, 1.0, 0.0], 20.0))
    assert h.call('capture').success
    assert len(h.node.session.samples) == 2


def test_manual_capture_with_stamps_behind_the_node_clock(harness_factory):
    """Stamps 5 s behind (another machine's clock): 'no paired poses in the last 1.0 s'."""
    cell = simulation.random_cell(np.random.default_rng(3))
    h = harness_factory([Parameter('capture_mode', value='manual'),
                         Parameter('still_window_s', value=0.2)])
    start = h.node.now_ns() - 5 * NS - int(0.5 * NS)
    h.publish_events(still_events(cell, cell.home, start, duration_s=0.5, rate_hz=40.0))
    captured = h.call('capture')
    assert captured.success, captured.message


@pytest.mark.parametrize('behind_s, paired', [(3.0, False), (1.5, True)])
def test_stamps_on_clocks_seconds_apart_are_named_with_the_offset_to_set(harness_factory,
                                                                         behind_s, paired):
    # Sensor stamps 3 s behind the robot's (two computers, no chrony): nothing paired and the
    # status stayed OK ('waiting for poses'); 1.5 s behind, poses paired with the wrong
    # partners within the link buffer, and only the residual said anything.
    cell = simulation.random_cell(np.random.default_rng(3))
    sensor = cell.sensor_pose(cell.home)
    h = harness_factory()
    # Stamped as they are sent, for 2 s: each pose arrives a transport delay after its stamp
    # (the sensor's behind_s more), whatever the load (stamps set beforehand and sent at once
    # made the lags depend on how long sending took). The last link poses wait for the status
    # timer's flush: timed at flush, they read 1 s late and the offset 1 s short.

    def send(count):
        for k in range(count):
            now = h.node.now_ns()
            h.publish('link_pose', now, cell.home)
            if k % 3 == 0:
                h.publish('sensor_pose', now - int(behind_s * NS), sensor)
            h.spin_for(0.01)
        h.wait_received()
    send(200)

    def warned(status):   # 1.5 s behind, pairs come once the link poses cover 1.5 s
        return (status.level == DiagnosticStatus.WARN and 'clocks' in status.message
                and (not paired or 'could be paired' not in status.message))
    status = h.next_status(warned)
    found = re.search(r'the sensor stamps run ([0-9.]+) s behind the link stamps, against the '
                      r'times their poses arrive: the two clocks are not synchronised \(.*set '
                      r'sensor_time_offset_s:=([0-9.]+),', status.message)
    assert found and found[1] == found[2], status.message
    assert abs(float(found[1]) - behind_s) < 0.3, status.message   # (the transport delays)
    assert ('could be paired; the latest: sensor stamp' in status.message) is not paired, \
        status.message
    # Set, the offset is judged with it: the warning goes.
    (changed,) = h.node.set_parameters([Parameter('sensor_time_offset_s', value=behind_s)])
    assert changed.successful
    send(20)
    h.next_status()   # (the period of the poses sent before the change ends)
    status = h.next_status()
    assert 'clocks are not synchronised' not in status.message, status.message


# --- parameters -----------------------------------------------------------------------------

def test_another_node_of_the_same_name_is_named_once(harness_factory):
    # Two calibrators of one name ran side by side without a word; ~/save reached either.
    h = harness_factory()
    other = rclpy.create_node('calibrator', context=h.context)
    try:
        h.spin_until(lambda: h.node.get_node_names_and_namespaces().count(
            ('calibrator', '/')) == 2, what='the other node discovered')
        expected = ('1 other node(s) named /calibrator run on this ROS domain: ~/save, ~/reset '
                    'and parameter changes may reach either; give each calibrator a name of '
                    'its own (--ros-args -r __node:=calibrator_2)')
        with logged_warnings(h.node) as warned:
            for _ in range(3):
                status = h.node.diagnostic_status()
        assert warned == [expected] and expected in status.message
        assert status.level == status.WARN
    finally:
        other.destroy_node()
    h.spin_until(lambda: h.node.get_node_names_and_namespaces().count(
        ('calibrator', '/')) == 1, what='the other node gone')
    assert 'other node(s) named' not in h.node.diagnostic_status().message


def test_invalid_parameters_are_refused_at_start(domain_id):
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        for name, value in (('setup', 'sideways'), ('still_window_s', -1.0),
                            ('capture_mode', 'never'), ('pose_type', 'odometry')):
            with pytest.raises(ConfigError, match=name):
                CalibratorNode(context=context,
                               parameter_overrides=[Parameter(name, value=value)])
        # Out of range in the table's words (rclpy's named the parameter twice).
        with pytest.raises(ConfigError, match=r'^parameter still_window_s must be between 0\.05 '
                                              r'and 10, not 20\.0$'):
            CalibratorNode(context=context,
                           parameter_overrides=[Parameter('still_window_s', value=20.0)])
        # A misspelled name was ignored without a word, and the default used.
        with pytest.raises(ConfigError, match=r'no such parameter: still_windw_s \(did you '
                                              r'mean still_window_s\?\)'):
            CalibratorNode(context=context,
                           parameter_overrides=[Parameter('still_windw_s', value=0.7)])
        # -p still_window_s:=1 is an integer, which ROS refuses for a real number: taken as
        # 1.0 (it was refused, with the remedy 'write 1.0').
        node = CalibratorNode(context=context,
                              parameter_overrides=[Parameter('still_window_s', value=1)])
        assert node.config.still_window_s == 1.0
        assert node.get_parameter('still_window_s').type_ == Parameter.Type.DOUBLE
        node.destroy_node()
        # A value of another type is refused in the table's words.
        with pytest.raises(ConfigError, match='^parameter still_window_s must be a number, '
                                              "not 'long'$"):
            CalibratorNode(context=context,
                           parameter_overrides=[Parameter('still_window_s', value='long')])
        # One like no parameter of its (a launch file's global robot_description) is said.
        node = CalibratorNode(context=context, parameter_overrides=[
            Parameter('robot_description', value='<robot/>')])
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_parameters_at_runtime(harness_factory, monkeypatch):
    h = harness_factory()
    node = h.node
    for parameter, words in ((Parameter('pairs', value='some'), 'pairs'),
                             (Parameter('max_gap_s', value=50.0), 'max_gap_s'),
                             (Parameter('pose_type', value='transform'), 'read-only'),
                             (Parameter('robust', value='no'), 'type')):
        (result,) = node.set_parameters([parameter])
        assert not result.successful and words in result.reason, result.reason
    assert node.config.pairs == 'all' and node.get_parameter('pairs').value == 'all'
    # A misspelt name is named, as at start (rclpy's refusal read 'undeclared parameter(s):
    # []'), and nothing is declared.
    (result,) = node.set_parameters([Parameter('still_windw_s', value=0.7)])
    assert not result.successful and result.reason == (
        'no such parameter: still_windw_s (did you mean still_window_s?); `calibrator --help` '
        'lists every parameter')
    (result,) = node.set_parameters([Parameter('colour', value='red')])
    assert result.reason == ('no such parameter: colour; `calibrator --help` lists every '
                             'parameter')
    assert not node.has_parameter('still_windw_s') and not node.has_parameter('colour')
    # `ros2 param set /calibrator still_window_s 1` sends an integer: taken as 1.0.
    (result,) = node.set_parameters([Parameter('still_window_s', value=1)])
    assert result.successful and node.config.still_window_s == 1.0
    assert node.get_parameter('still_window_s').type_ == Parameter.Type.DOUBLE
    (result,) = node.set_parameters([Parameter('pairs', value='consecutive')])
    assert result.successful
    assert node.config.pairs == 'consecutive'
    assert node.session.config.calibration.pairs == 'consecutive'
    # The moved-marker watch learns where capture became continuous (its samples are
    # noisier: a rise there is said to be that first).
    for mode in ('continuous', 'auto', 'continuous'):
        (result,) = node.set_parameters([Parameter('capture_mode', value=mode)])
        assert result.successful
    assert node.moves.continuous_from == [0, 0]
    (result,) = node.set_parameters([Parameter('link_frame', value='flange')])
    assert result.successful and node.config.link_frame == 'flange'
    # With an estimate, a new result frame republishes it between the new frames (the
    # topics and /tf_static kept the old frame until the next estimate, ~/save had the new)
    sent, estimate = [], object()
    node.publish_estimate = sent.append
    monkeypatch.setattr(CalibratorNode, 'result', property(lambda self: estimate))
    (result,) = node.set_parameters([Parameter('sensor_frame', value='camera_optical')])
    assert result.successful and sent == [estimate]
    (result,) = node.set_parameters([Parameter('plan_view_cone_deg', value=25.0)])
    assert result.successful and len(sent) == 1
    # eye_to_hand with link_frame at its default: the parent is link_frame_id's frame
    result = node.set_parameters_atomically([Parameter('setup', value='eye_to_hand'),
                                            Parameter('link_frame', value='tool0')])
    assert result.successful and len(sent) == 1   # a new session: nothing to republish yet
    (result,) = node.set_parameters([Parameter('link_frame_id', value='world')])
    assert result.successful and node.config.result_frames == ('world', 'camera_optical')
    assert sent == [estimate, estimate]


def test_transform_messages_with_pose_type_transform(harness_factory):
    h = harness_factory([Parameter('pose_type', value='transform')],
                        message_type=TransformStamped)
    cell = simulation.random_cell(np.random.default_rng(6))
    h.publish_events(still_events(cell, cell.home, simulation.DEFAULT_START_NS))
    h.spin_until(lambda: len(h.node.session.samples) == 1, what='a sample from transforms')


@pytest.mark.parametrize('parameter', ['pose_type', 'sensor_pose_type'])
def test_pose_with_covariance_messages_weight_the_samples(harness_factory, parameter):
    """
    Sensor poses with covariance: each sample keeps its covariance; bad ones are named.

    pose_type: both topics carry it; sensor_pose_type: only sensor_pose (the target_detector's
    poses beside a robot's PoseStamped).
    """
    both = parameter == 'pose_type'
    h = harness_factory([Parameter(parameter, value='pose_with_covariance')],
                        message_type=PoseWithCovarianceStamped if both else PoseStamped,
                        sensor_type=PoseWithCovarianceStamped)
    rng = np.random.default_rng(6)
    cell = simulation.random_cell(rng)
    covariance = np.diag([1e-6, 1e-6, 9e-6, 3e-6, 3e-6, 1e-7])   # ROS order, m^2 and rad^2
    start = simulation.DEFAULT_START_NS
    events = []
    for k, link in enumerate(simulation.stop_poses(rng, cell, 6)):
        events += [(stream, stamp, Pose(pose.position, pose.quaternion, (k + 1) * covariance)
                    if stream == 'sensor_pose' else pose)
                   for stream, stamp, pose in still_events(cell, link, start + k * 2 * NS)]
    h.publish_events(events)
    h.spin_until(lambda: len(h.node.session.samples) == 6, what='six samples')
    for k, sample in enumerate(h.node.session.samples):
        np.testing.assert_allclose(sample.sensor.covariance, (k + 1) * covariance, rtol=1e-12)
    h.spin_until(lambda: h.node.session.result is not None, what='an estimate')
    assert h.node.session.result.noise_model['sample_covariances'] == 'input'
    # The planner's next pose, on ~/next_pose (latched, robot base frame) and /diagnostics.
    proposals = []
    h.driver.create_subscription(PoseStamped, '/calibrator/next_pose', proposals.append,
                                 LATCHED)
    h.spin_until(lambda: proposals, what='~/next_pose')
    assert proposals[-1].header.frame_id == 'base_link'
    values = {kv.key: kv.value for kv in h.node.diagnostic_status().values}
    assert values['next_pose'].startswith('position ') and 'expected uncertainty' in \
        values['next_pose']
    # Beside the model's figure now: the reported (measured) one can be smaller than the
    # model's expected after the pose, which read as a proposal that makes it worse.
    assert "(the model's figures: now " in values['next_pose']
    bad = conversions.pose_with_covariance_stamped_msg(cell.home, start + 20 * NS, 'camera')
    bad.pose.covariance[7] = -1.0   # not positive definite
    h.sensor_pub.publish(bad)
    h.spin_until(lambda: h.node.stats.bad[('sensor_pose', 'bad_covariance')] == 1,
                 what='the bad covariance counted')
    # A change that leaves no estimate leaves no next pose in /diagnostics either.
    (changed,) = h.node.set_parameters([Parameter('min_motion_deg', value=90.0)])
    assert changed.successful
    h.spin_until(lambda: h.node.session.result is None, what='no estimate at 90 deg')
    values = {kv.key: kv.value for kv in h.node.diagnostic_status().values}
    assert values['state'] == 'collecting' and values['next_pose'] == ''


def test_topic_names_follow_namespace_and_remapping(domain_id):
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        node = CalibratorNode(context=context, namespace='cell1',
                              cli_args=['--ros-args', '-r', 'link_pose:=/robot/tool_pose'])
        topics = {sub.topic_name for sub in node.subscriptions}
        assert topics == {'/robot/tool_pose', '/cell1/sensor_pose'}
        assert node.rotation_publisher.topic_name == '/cell1/calibrator/rotation'
        assert {srv.service_name for srv in node.services} >= {
            '/cell1/calibrator/capture', '/cell1/calibrator/reset', '/cell1/calibrator/save'}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


# --- bad input ------------------------------------------------------------------------------

def test_bad_messages_are_counted_not_fatal(harness_factory, monkeypatch):
    h = harness_factory([Parameter('diagnostics_period_s', value=0.2)])
    deserialised = []   # the messages the node's own decoder left to rclpy

    def deserialise(raw, kind):
        deserialised.append(raw)
        return deserialize_message(raw, kind)
    monkeypatch.setattr(inputs, 'deserialize_message', deserialise)
    bad = []
    nan_pose = PoseStamped()
    nan_pose.pose.position.x = float('nan')
    nan_pose.pose.orientation.w = 1.0
    bad.append((h.link_pub, nan_pose))
    zero_q = PoseStamped()
    zero_q.pose.orientation.w = 0.0      # all zero: a zero quaternion
    bad.append((h.sensor_pub, zero_q))
    unnormalised = PoseStamped()
    unnormalised.pose.orientation.w = 2.0
    bad.append((h.sensor_pub, unnormalised))
    for publisher, msg in bad:
        msg.header.stamp.sec = 10
        publisher.publish(msg)
    h.spin_until(lambda: h.node.stats.bad_total == 3, what='three bad messages counted')
    assert h.node.stats.bad[('link_pose', 'non_finite')] == 1
    assert h.node.stats.bad[('sensor_pose', 'zero_quaternion')] == 1
    assert h.node.stats.bad[('sensor_pose', 'non_unit_quaternion')] == 1
    h.diagnostics.clear()
    h.spin_until(lambda: h.diagnostics, what='diagnostics')
    values = {kv.key: kv.value for kv in h.diagnostics[-1].status[0].values}
    assert values['bad_messages'] == '3'
    assert values['bad_link_pose_non_finite'] == '1'
    assert values['bad_sensor_pose_zero_quaternion'] == '1'
    assert values['link_messages'] == '1' and values['sensor_messages'] == '2'
    # Bytes that are not a PoseStamped at all, and one whose frame is not the configured one
    # (read by the node's own decoder: the same checks and counts as a message).
    h.link_pub.publish(b'\x00\x01\x00\x00not a pose')
    h.spin_until(lambda: h.node.stats.bad_total == 4, what='undecodable bytes counted')
    assert h.node.stats.bad[('link_pose', 'undecodable')] == 1
    h.node.set_parameters([Parameter('link_frame_id', value='base_link')])
    elsewhere = PoseStamped()
    elsewhere.header.frame_id, elsewhere.header.stamp.sec = 'world', 11
    elsewhere.pose.orientation.w = 1.0
    h.link_pub.publish(elsewhere)
    h.spin_until(lambda: h.node.stats.bad_total == 5, what='wrong frame id counted')
    assert h.node.stats.bad[('link_pose', 'wrong_frame_id')] == 1
    h.node.set_parameters([Parameter('link_frame_id', value='')])
    assert len(deserialised) == 4   # the bad numbers and the bytes; not the frame id
    # Still alive: a good still stream is captured afterwards.
    rng = np.random.default_rng(4)
    cell = simulation.random_cell(rng)
    h.publish_events(still_events(cell, cell.home, simulation.DEFAULT_START_NS))
    h.spin_until(lambda: len(h.node.session.samples) == 1, what='a sample after bad input')
    assert len(deserialised) == 4   # every good pose read by the node's decoder


def test_frames_that_contradict_the_inputs_or_the_result_are_warned_once(harness_factory,
                                                                         capfd):
    # A transform link pose ending in another link, and sensor poses measured in the
    # camera's optical frame: the node's defaults (tool0 -> camera) would publish the
    # estimate under frames it does not describe.
    h = harness_factory([Parameter('pose_type', value='transform')],
                        message_type=TransformStamped)
    h.FRAMES = {'link_pose': ('/base_link', 'flange'),
                'sensor_pose': ('camera_color_optical_frame', 'marker')}
    cell = simulation.random_cell(np.random.default_rng(8))
    start = simulation.DEFAULT_START_NS
    for stop in range(2):   # each status judges the messages since the one before
        h.publish_events(still_events(cell, cell.home, start + stop * 2 * NS))
        status = h.node.diagnostic_status()
        assert status.level == DiagnosticStatus.WARN
        assert "the estimate's parent frame is 'flange', but it is published as 'tool0' " \
            '(link_frame)' in status.message and 'set link_frame:=flange' in status.message
        assert 'set sensor_frame:=camera_color_optical_frame (unless that is the robot base: ' \
            'then the link_pose and sensor_pose topics are swapped)' in status.message
    logged = [line for line in capfd.readouterr().err.splitlines()
              if line.startswith('[WARN]') and 'a frame it does not describe' in line]
    assert len(logged) == 2   # each said once, though every status repeats it
    # Named as the messages name them (a leading slash or not), the warnings go.
    assert h.node.set_parameters_atomically([
        Parameter('link_frame', value='flange'),
        Parameter('sensor_frame', value='/camera_color_optical_frame')]).successful
    h.publish_events(still_events(cell, cell.home, start + 4 * NS))
    assert 'does not describe' not in h.node.diagnostic_status().message
    # So does a publisher put right, with the next status.
    (done,) = h.node.set_parameters([Parameter('link_frame', value='tool0')])
    assert done.successful
    h.publish_events(still_events(cell, cell.home, start + 6 * NS))
    assert 'set link_frame:=flange' in h.node.diagnostic_status().message
    h.FRAMES = dict(h.FRAMES, link_pose=('base_link', 'tool0'))
    h.publish_events(still_events(cell, cell.home, start + 8 * NS))
    assert 'does not describe' not in h.node.diagnostic_status().message


def test_a_link_pose_in_the_sensor_frame_is_taken_for_swapped_topics(harness_factory):
    h = harness_factory()
    h.FRAMES = {'link_pose': ('camera', None), 'sensor_pose': ('base_link', None)}
    cell = simulation.random_cell(np.random.default_rng(9))
    h.publish_events(still_events(cell, cell.home, simulation.DEFAULT_START_NS))
    status = h.node.diagnostic_status()
    assert status.level == DiagnosticStatus.WARN
    assert 'are the link_pose and sensor_pose topics swapped?' in status.message
    assert len(h.node.session.samples) == 1   # a warning: the poses are still used


def test_messages_lost_before_the_node_read_them_are_counted(harness_factory):
    # A burst of link poses while the node does not spin: its queue (1000) overflows. The
    # publisher numbers its messages; the gaps are counted, received + lost = sent. (No
    # status on the node's timer: each status says the loss since the one before.)
    h = harness_factory([Parameter('diagnostics_period_s', value=60.0)])
    subscription = h.node.inputs._numbered['link_pose']
    h.spin_until(lambda: subscription.get_publisher_count() == 1, what='the publisher')
    h.node.diagnostic_status()   # the stream has one publisher: its numbers count
    start, sent = simulation.DEFAULT_START_NS, 2_500
    stats = h.node.stats
    h.publish('link_pose', start, Pose.identity())   # the first number seen
    taken = h.node.inputs.flush   # (link poses are held a moment, then decoded together)
    h.spin_until(lambda: taken() or stats.received['link_pose'] == 1, what='the first pose')
    for k in range(1, sent):
        h.publish('link_pose', start + k * NS // 1000, Pose.identity())
    h.spin_until(lambda: taken() or stats.received['link_pose'] + stats.lost['link_pose'] == sent,
                 what='every message received or counted lost')
    lost = stats.lost['link_pose']
    assert lost >= sent - 1 - 1_000 and stats.lost['sensor_pose'] == 0
    status = h.node.diagnostic_status()
    values = {kv.key: kv.value for kv in status.values}
    assert values['link_messages_lost'] == str(lost) and values['sensor_messages_lost'] == '0'
    assert status.level == DiagnosticStatus.WARN
    assert f'/link_pose: {lost} of the {sent} messages sent since the last status ' \
        f'({100 * lost / sent:.1f} %) were lost before the node read them' in status.message
    # Said for the period it happened in only.
    assert 'lost before' not in h.node.diagnostic_status().message
    # A second publisher: their numbers interleave (3, 1, 4, 2, ...), and the count stops;
    # what was counted stays.
    second = h.driver.create_publisher(PoseStamped, 'link_pose', RELIABLE)
    h.spin_until(lambda: subscription.get_publisher_count() == 2, what='a second publisher')
    for k in range(20):
        (h.link_pub if k % 2 else second).publish(conversions.pose_stamped_msg(
            Pose.identity(), start + (sent + k) * NS // 1000, 'base_link'))
    h.spin_until(lambda: taken() or stats.received['link_pose'] == sent - lost + 20,
                 what='the two publishers')
    values = {kv.key: kv.value for kv in h.node.diagnostic_status().values}
    assert values['link_messages_lost'] == str(lost) and values['sensor_messages_lost'] == '0'
    second.destroy()


# --- as processes ---------------------------------------------------------------------------

def _tool_command(tool):
    if (REPO_ROOT / 'quatcal_ros' / '__main__.py').exists():
        return [sys.executable, '-m', 'quatcal_ros', tool]
    module = {'calibrator': 'quatcal_ros.ros.node', 'sim_cell': 'quatcal_ros.ros.sim_cell'}[tool]
    return [sys.executable, '-c', f'import sys; from {module} import main; sys.exit(main())']


def _process_env(domain_id):
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    env['PYTHONPATH'] = os.pathsep.join(
        [str(REPO_ROOT)] + [p for p in [env.get('PYTHONPATH')] if p])
    return env


_STARTED = []   # the processes of the running test (_start)


@pytest.fixture(autouse=True)
def no_process_outlives_its_test():
    """Kill what a test started and left running (a failed assert before its stop)."""
    yield
    while _STARTED:
        process = _STARTED.pop()
        if process.poll() is None:
            process.kill()
            process.wait()


def _start(tool, *ros_args, log_path, domain_id):
    command = _tool_command(tool) + (['--ros-args', *ros_args] if ros_args else [])
    process = subprocess.Popen(command, env=_process_env(domain_id), cwd=REPO_ROOT,
                               stdout=log_path.open('w'), stderr=subprocess.STDOUT)
    _STARTED.append(process)
    return process


def _wait_for_the_signal_guard(process, timeout=60.0):
    """
    Wait until `process` catches SIGTERM (its SigCgt mask in /proc): the tool's first line.

    Python itself catches SIGINT from its start; SIGTERM only the tool's guard (__main__.py).
    """
    deadline = time.monotonic() + timeout
    status = Path(f'/proc/{process.pid}/status')
    while time.monotonic() < deadline and process.poll() is None:
        caught = [line for line in status.read_text().splitlines()
                  if line.startswith('SigCgt:')]
        if caught and int(caught[0].split()[1], 16) >> (signal.SIGTERM - 1) & 1:
            return
        time.sleep(0.005)
    raise AssertionError('the process never caught SIGTERM')


class Listener(ProcessWatcher):
    """A node in the test process that listens to the processes' outputs."""

    def __init__(self, domain_id):
        super().__init__('test_listener', domain_id)
        self.truths = []
        self.node.create_subscription(TransformStamped, '/sim_cell/ground_truth',
                                      self.truths.append, LATCHED)


def test_processes_converge_to_the_ground_truth_and_exit_cleanly(tmp_path, process_domain_id):
    sim = _start('sim_cell', '-p', 'seed:=4', '-p', 'still_s:=0.6', '-p', 'move_s:=0.6',
                 '-p', 'link_rate_hz:=100.0', '-p', 'rotation_spread_deg:=40.0',
                 log_path=tmp_path / 'sim.log', domain_id=process_domain_id)
    calibrator = _start('calibrator', '-p', 'still_window_s:=0.3',
                        '-p', 'diagnostics_period_s:=0.5', log_path=tmp_path / 'calib.log',
                        domain_id=process_domain_id)
    listener = Listener(process_domain_id)
    processes = (sim, calibrator)
    try:
        def converged():
            if not (listener.rotations and listener.truths and listener.statuses):
                return False
            values = {kv.key: kv.value for kv in listener.statuses[-1].values}
            return values['uncertainty_deg'] and float(values['uncertainty_deg']) < 0.2
        listener.spin_until(converged, 60.0, 'an uncertainty below 0.2 deg', processes)
        values = {kv.key: kv.value for kv in listener.statuses[-1].values}
        uncertainty = float(values['uncertainty_deg'])
        truth = conversions.pose_from_msg(listener.truths[-1]).quaternion
        estimate = rotation_of(listener.rotations[-1])
        assert listener.rotations[-1].header.frame_id == 'tool0'
        assert angle_deg(estimate, truth) < 3.0 * uncertainty + 0.05
    finally:
        codes = [stop_process(process, signal.SIGINT) for process in processes]
        listener.close()
    logs = (tmp_path / 'calib.log').read_text()
    assert codes == [0, 0], logs
    assert 'sample 0 captured' in logs and 'estimate:' in logs


def test_process_exits_cleanly_on_sigterm_and_refuses_bad_parameters(tmp_path,
                                                                     process_domain_id):
    bad = subprocess.run(
        _tool_command('calibrator') + ['--ros-args', '-p', 'setup:=sideways'],
        env=_process_env(process_domain_id), cwd=REPO_ROOT, capture_output=True, text=True,
        timeout=60)
    assert bad.returncode != 0
    assert 'setup' in bad.stdout + bad.stderr and 'sideways' in bad.stdout + bad.stderr
    calibrator = _start('calibrator', log_path=tmp_path / 'calib.log',
                        domain_id=process_domain_id)
    deadline = time.monotonic() + 30.0
    while 'calibrating' not in (tmp_path / 'calib.log').read_text():
        assert calibrator.poll() is None and time.monotonic() < deadline
        time.sleep(0.1)
    assert stop_process(calibrator, signal.SIGTERM) == 0


def test_a_renamed_node_logs_its_fatal_start_up_error_under_its_own_name(
        tmp_path, process_domain_id):
    process = _start('calibrator', '-r', '__node:=calibrator2', '-p', 'setup:=sideways',
                     log_path=tmp_path / 'calib.log', domain_id=process_domain_id)
    assert process.wait(timeout=60) == 2
    log = (tmp_path / 'calib.log').read_text()
    assert '[calibrator2]: invalid parameters: parameter setup must be one of' in log, log


def test_node_name_reads_the_remapping():
    from quatcal_ros.ros.spin import node_name
    assert node_name(['calibrator', '--ros-args', '-r', '__node:=cal2'], 'calibrator') == 'cal2'
    assert node_name(['calibrator', '--ros-args', '-p', 'x:=1'], 'calibrator') == 'calibrator'
    assert node_name(['x', '-r', 'link_pose:=/a', '--remap', '__name:=b'], 'c') == 'b'


# While the interpreter itself starts (about 30 ms here, more under load) a signal ends any
# Python program; from the tool's first line on it is noted (__main__.py): the delays count
# from then, so that a busy machine cannot move the signal before it.
@pytest.mark.parametrize('tool, signum, delay_s', [
    ('calibrator', signal.SIGINT, 0.0), ('calibrator', signal.SIGTERM, 0.05),
    ('calibrator', signal.SIGINT, 0.3), ('calibrator', signal.SIGTERM, 0.7),
    ('sim_cell', signal.SIGINT, 0.0), ('sim_cell', signal.SIGTERM, 0.4),
])
def test_a_stop_signal_at_any_moment_of_start_up_exits_0(
        tmp_path, process_domain_id, tool, signum, delay_s):
    """While the tool imports, builds its node or spins: SIGINT and SIGTERM end it with 0."""
    process = _start(tool, log_path=tmp_path / 'log', domain_id=process_domain_id)
    _wait_for_the_signal_guard(process)
    time.sleep(delay_s)   # when the signal comes; any moment after the guard must do
    process.send_signal(signum)
    assert process.wait(timeout=60) == 0, (tmp_path / 'log').read_text()
    assert 'Traceback' not in (tmp_path / 'log').read_text()


def test_a_stale_stream_is_logged_once_while_its_seconds_grow():
    # A remapped topic that never sent: /diagnostics said so, the log stayed silent.
    from quatcal_ros.ros.node import without_numbers
    from quatcal_ros.stream.log_throttle import StandingLog
    log = StandingLog(5e9, key=without_numbers)
    texts = ['link_pose stale: no message on /robot/tool_pose at all in {:.1f} s'.format(s)
             for s in (3.1, 5.9, 8.4, 12.0)]
    assert [log.due([text], now) for text, now in zip(texts, (0, 3e9, 5e9, 9e9))] == [
        [], [], [texts[2]], []]


def test_publishers_of_the_wrong_type_are_named(domain_id):
    from geometry_msgs.msg import PointStamped
    h = Harness(domain_id)
    other = Context()   # a participant of its own: one may not hold a topic in two types
    rclpy.init(context=other, domain_id=domain_id)
    try:
        wrong = rclpy.create_node('wrong_type', context=other)
        wrong.create_publisher(PointStamped, 'sensor_pose', RELIABLE)
        h.spin_until(lambda: 'geometry_msgs/msg/PointStamped' in [
            info.topic_type for info in h.node.get_publishers_info_by_topic('/sensor_pose')],
            what='the wrong-type publisher in the graph')
        # Silent for long enough to be stale: the type explains it, the topic and the
        # publisher are right ('is it remapped ..., does the publisher run?' sent the user
        # to check them); the link stream, silent with no publisher at all, keeps its advice.
        h.node.input_watch.started_ns = h.node.now_ns() - 10 * NS_PER_S
        h.node.diagnostic_status()   # (the graph's verdict, at the status before)
        status = h.node.diagnostic_status()
        assert status.level == DiagnosticStatus.WARN
        assert '/sensor_pose has publishers of type geometry_msgs/msg/PointStamped; the node ' \
            'subscribes geometry_msgs/msg/PoseStamped (parameter pose_type, or ' \
            'sensor_pose_type)' in status.message
        assert 'no message on /sensor_pose' not in status.message, status.message
        assert 'no message on /link_pose' in status.message, status.message
        assert 'sensor_pose' in {kv.key: kv.value for kv in status.values}['stale'].split()
        # Only /diagnostics said so; the log is told once it has stood a while, then once.
        h.node._input_log.after = 0   # (as if it had stood INPUT_PROBLEM_LOG_S)
        with logged_warnings(h.node) as warned:
            h.node.diagnostic_status()
            h.node.diagnostic_status()
        said = [w for w in warned if w.startswith('/sensor_pose has publishers of type '
                                                  'geometry_msgs/msg/PointStamped')]
        assert len(said) == 1, warned
        wrong.destroy_node()
    finally:
        rclpy.try_shutdown(context=other)
        h.close()


def test_a_best_effort_link_publisher_is_named(domain_id):
    """The link subscription is reliable: a best-effort publisher is heard by no one."""
    h = Harness(domain_id)
    try:
        def link_publishers():
            return [info.qos_profile.reliability
                    for info in h.node.get_publishers_info_by_topic('/link_pose')]
        h.driver.destroy_publisher(h.link_pub)
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        h.driver.create_publisher(PoseStamped, 'link_pose', best_effort)
        h.spin_until(lambda: link_publishers() == [ReliabilityPolicy.BEST_EFFORT],
                     what='only the best-effort publisher in the graph')
        status = h.node.diagnostic_status()
        assert status.level == DiagnosticStatus.WARN
        assert '/link_pose has only best-effort publishers (1); the node subscribes it ' \
            'reliable' in status.message
        h.driver.create_publisher(PoseStamped, 'link_pose', RELIABLE)   # one it hears
        h.spin_until(lambda: len(link_publishers()) == 2, what='the reliable publisher')
        assert 'best-effort' not in h.node.diagnostic_status().message
    finally:
        h.close()


def test_a_position_beyond_the_bound_is_counted_not_used(domain_id):
    h = Harness(domain_id, [Parameter('max_position_m', value=100.0)])
    try:
        h.publish('link_pose', 10 * NS_PER_S, Pose.create([1e308, 0.0, 0.0], [1, 0, 0, 0]))
        h.publish('link_pose', 11 * NS_PER_S, Pose.create([150.0, 0.0, 0.0], [1, 0, 0, 0]))
        h.spin_until(lambda: h.node.stats.bad_total == 2, what='two implausible positions')
        assert h.node.stats.bad == {('link_pose', 'implausible_position'): 2}
    finally:
        h.close()


def test_without_a_clock_the_status_still_comes_and_says_so(domain_id):
    h = Harness(domain_id, [Parameter('use_sim_time', value=True),
                            Parameter('diagnostics_period_s', value=0.2)])
    try:
        h.spin_until(lambda: h.diagnostics, what='/diagnostics without /clock')
        (status,) = h.diagnostics[-1].status
        assert 'no /clock message has come' in status.message
    finally:
        h.close()


def test_a_clock_that_stopped_is_named():
    # /clock stopped (a paused bag): the status stayed OK with nothing stale for 30 s
    from quatcal_ros.ros.diagnostics import InputWatch
    from quatcal_ros.stream.message_checks import StreamStats
    watch = InputWatch({}, 1)
    args = (StreamStats(), {}, lambda topic: [], 0)
    assert watch.problems(*args, 5 * NS_PER_S, True, steady_ns=100 * NS_PER_S) == []
    assert watch.problems(*args, 5 * NS_PER_S, True, steady_ns=102 * NS_PER_S) == []
    (said,) = watch.problems(*args, 5 * NS_PER_S, True, steady_ns=104 * NS_PER_S)
    assert '/clock has stood at 5.000 s for 4 s' in said
    assert watch.problems(*args, 6 * NS_PER_S, True, steady_ns=105 * NS_PER_S) == []
    assert watch.problems(*args, 6 * NS_PER_S, False, steady_ns=200 * NS_PER_S) == []


def test_a_publisher_replaced_after_the_stream_had_data_is_named():
    """A link driver restarted best effort: the stream had data, so it was never checked."""
    from types import SimpleNamespace
    from quatcal_ros.ros.diagnostics import InputWatch
    from quatcal_ros.stream.message_checks import StreamStats
    expected = 'geometry_msgs/msg/PoseStamped'
    watch = InputWatch({'link_pose': expected, 'sensor_pose': expected}, 1,
                       reliable={'link_pose'})
    stats = StreamStats()
    for stream in ('link_pose', 'sensor_pose'):
        stats.note(stream, 1 * NS_PER_S)
    stats.note('sensor_pose', 9 * NS_PER_S)
    best_effort = [SimpleNamespace(topic_type=expected, qos_profile=SimpleNamespace(
        reliability=ReliabilityPolicy.BEST_EFFORT))]
    topics = {'link_pose': '/link_pose', 'sensor_pose': '/sensor_pose'}
    (said,) = watch.problems(stats, topics, lambda topic: best_effort, 0, 10 * NS_PER_S, False)
    assert said.startswith('/link_pose has only best-effort publishers (1)')
    stats.note('link_pose', 10 * NS_PER_S)   # heard again: nothing to say
    stats.note_good('link_pose', 10 * NS_PER_S)
    assert watch.problems(stats, topics, lambda topic: best_effort, 0, 10 * NS_PER_S,
                          False) == []


def test_the_status_is_named_after_the_node(domain_id, tmp_path):
    # Two calibrators on one domain published the same status name
    from quatcal_ros.ros.diagnostics import DIAGNOSTIC_NAME
    assert DIAGNOSTIC_NAME == 'calibrator: hand-eye rotation'   # the default node's
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        node = CalibratorNode(context=context, cli_args=['--ros-args', '-r', '__node:=cal_left'],
                              parameter_overrides=[
                                  Parameter('samples_file', value=str(tmp_path / 's.csv'))])
        try:
            assert node.diagnostic_status().name == 'cal_left: hand-eye rotation'
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_two_clocks_on_one_stream_are_named(domain_id):
    h = Harness(domain_id)
    try:
        pose = Pose.create([0.1, 0.2, 0.3], [1, 0, 0, 0])
        h.node.diagnostic_status()   # the status period starts
        for k in range(8):   # a second publisher stamping one second earlier
            h.publish('sensor_pose', (100 + k) * NS_PER_S // 10 + (k % 2) * -NS_PER_S, pose)
        h.wait_received()
        # each message of the second clock is behind, and the next one goes on: stale ones
        assert h.node.stats.bad[('sensor_pose', 'stale_stamp')] >= 3
        status = h.node.diagnostic_status()
        assert 'single messages far behind, dropped): two publishers with different clocks ' \
            'on one stream?' in status.message
        assert status.level == DiagnosticStatus.WARN
    finally:
        h.close()


def test_without_home_rcl_gets_a_log_directory(monkeypatch, tmp_path, capsys):
    from quatcal_ros.ros import spin
    for name in ('HOME', 'ROS_HOME', 'ROS_LOG_DIR'):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(spin.os.path, 'expanduser', lambda path: str(tmp_path))
    spin._ensure_log_directory()
    assert os.environ['ROS_HOME'] == str(tmp_path / '.ros')
    assert 'HOME is not set' in capsys.readouterr().err
    monkeypatch.setattr(spin.os.path, 'expanduser', lambda path: path)   # no pwd entry
    monkeypatch.delenv('ROS_HOME')
    spin._ensure_log_directory()
    assert os.environ['ROS_HOME'].endswith('.ros') and os.environ['ROS_HOME'] != '~/.ros'
