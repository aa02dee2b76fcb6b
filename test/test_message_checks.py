"""
Tests of bad pose messages: the core checks (message_checks) and the node that applies them.

Core tests run on plain numbers.  Node tests build the calibrator in a private Context and
publish through the middleware (on a domain id of conftest): every kind of bad message is
counted under its stream and reason in /diagnostics, logged with the topic and the reason
(throttled per both), and skipped, and good data afterwards is still used.  A flood of bad
messages on a live node is tested in test_soak.py.
"""

import re
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import MESSAGE_NORM_TOLERANCE, NS_PER_S
from quatcal_ros.ros import conversions
from quatcal_ros.ros.diagnostics import DIAGNOSTIC_NAME
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.sim import simulation
from quatcal_ros.stream import message_checks as mc
from quatcal_ros.stream.log_throttle import LOG_THROTTLE_S
from quatcal_ros.stream.session import Notice
from quatcal_ros.stream.session import Rejected
from quatcal_ros.stream.session import Session
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.qos import ReliabilityPolicy
from ros_harness import logged_warnings, SpinMixin
from rosgraph_msgs.msg import Clock

NS = NS_PER_S
MS = 1_000_000
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


# --- the core checks -------------------------------------------------------------------------

def test_stamp_reason():
    now = 1_800_000_000 * NS
    limit = 30 * NS
    assert mc.stamp_reason(now, now, limit) is None
    assert mc.stamp_reason(now + limit, now, limit) is None
    assert mc.stamp_reason(now - limit, now, limit) is None
    assert mc.stamp_reason(0, now, limit) == 'zero_stamp'
    assert mc.stamp_reason(0, now, 0) == 'zero_stamp'
    assert mc.stamp_reason(now + limit + 1, now, limit) == 'stamp_in_future'
    assert mc.stamp_reason(now - limit - 1, now, limit) == 'stamp_in_past'
    assert mc.stamp_reason(-5 * NS, now, limit) == 'stamp_in_past'
    # 0 turns the clock check off; so does a node clock that has not started (use_sim_time).
    assert mc.stamp_reason(now - 10 ** 6 * NS, now, 0) is None
    assert mc.stamp_reason(now, 0, limit) is None


def test_frame_reason_and_check():
    assert mc.frame_reason('anything', '') is None
    assert mc.frame_reason('camera', 'camera') is None
    assert mc.frame_reason('/camera', 'camera') is None
    assert mc.frame_reason('camera_optical', 'camera') == 'wrong_frame_id'
    assert mc.frame_reason('', 'camera') == 'wrong_frame_id'
    config = mc.CheckConfig(max_stamp_offset_ns=NS, link_frame_id='base',
                            sensor_frame_id='camera')
    now = 100 * NS
    assert mc.check(mc.LINK, now, 'base', now, config) is None
    assert mc.check(mc.LINK, now, 'camera', now, config) == 'wrong_frame_id'
    assert mc.check(mc.SENSOR, now, 'camera', now, config) is None
    # The stamp is checked first.
    assert mc.check(mc.SENSOR, 0, 'base', now, config) == 'zero_stamp'
    with pytest.raises(ValueError, match='max_stamp_offset_ns'):
        mc.CheckConfig(max_stamp_offset_ns=-1)


def test_describe_says_what_to_do():
    config = mc.CheckConfig(max_stamp_offset_ns=30 * NS, sensor_frame_id='camera')
    now = 1_000 * NS
    text = mc.describe('stamp_in_future', mc.SENSOR, now + 45 * NS, 'camera', now, config)
    assert '45 s ahead of the node clock' in text and 'max_stamp_offset_s' in text
    text = mc.describe('stamp_in_past', mc.SENSOR, now - 45 * NS, 'camera', now, config)
    assert '45 s behind the node clock' in text and 'use_sim_time' in text
    text = mc.describe('wrong_frame_id', mc.SENSOR, now, 'world', now, config)
    assert "'world' is not 'camera'" in text and 'sensor_frame_id' in text
    text = mc.describe('wrong_frame_id', mc.SENSOR, now, 'w' * 1_000_000, now, config)
    assert f"'{'w' * (mc.MAX_LOGGED_CHARACTERS - 3)}...' is not 'camera'" in text
    assert 'stamp' in mc.describe('zero_stamp', mc.LINK)
    assert mc.diagnostic_key(mc.LINK, 'zero_stamp') == 'bad_link_pose_zero_stamp'


def _msg(position=(0.0, 0.0, 0.0), xyzw=(0.0, 0.0, 0.0, 1.0), sec=10, nanosec=0,
         frame_id='base'):
    msg = PoseStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.header.frame_id = frame_id
    p, q = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = position
    q.x, q.y, q.z, q.w = xyzw
    return msg


@pytest.mark.parametrize('position, xyzw, reason', [
    ((float('nan'), 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 'non_finite'),
    ((0.0, 0.0, float('-inf')), (0.0, 0.0, 0.0, 1.0), 'non_finite'),
    ((0.0, 0.0, 0.0), (0.0, float('inf'), 0.0, 1.0), 'non_finite'),
    ((1e308, 1e308, 0.0), (0.0, 0.0, 0.0, 1.0), None),     # huge but finite: a pose
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), 'zero_quaternion'),
    ((0.0, 0.0, 0.0), (1e-9, 0.0, 0.0, 0.0), 'zero_quaternion'),
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 2.0), 'non_unit_quaternion'),
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.99), 'non_unit_quaternion'),
    ((0.0, 0.0, 0.0), (1e200, 1e200, 0.0, 0.0), 'non_unit_quaternion'),
])
def test_bad_poses_carry_their_reason(position, xyzw, reason):
    if reason is None:
        assert conversions.pose_from_msg(_msg(position, xyzw)).position[0] == 1e308
        return
    with pytest.raises(conversions.BadPoseError) as error:
        conversions.pose_from_msg(_msg(position, xyzw))
    assert mc.pose_error_reason(error.value) == reason
    assert error.value.field.startswith('pose.')


def test_slightly_off_quaternion_is_renormalised():
    s = 1.0 + 0.5 * MESSAGE_NORM_TOLERANCE
    pose = conversions.pose_from_msg(_msg(xyzw=(0.0, 0.6 * s, 0.0, 0.8 * s)))
    np.testing.assert_allclose(pose.quaternion, [0.8, 0.0, 0.6, 0.0], atol=1e-15)
    assert np.linalg.norm(pose.quaternion) == pytest.approx(1.0, abs=1e-15)


def test_fast_and_slow_paths_agree():
    rng = np.random.default_rng(8)
    for _ in range(200):
        q = rng.normal(size=4)
        q *= rng.uniform(0.998, 1.002) / np.linalg.norm(q)
        p = rng.normal(size=3) * 10.0
        try:
            got = conversions.validate_pose_numbers(p, q)
        except conversions.BadPoseError:
            got = None
        try:
            slow = conversions._validate_slowly(p, q, MESSAGE_NORM_TOLERANCE,
                                                'position', 'orientation')
        except conversions.BadPoseError:
            slow = None
        assert (got is None) == (slow is None)
        if got is not None:
            np.testing.assert_allclose(got[0], slow[0], rtol=0, atol=0)
            np.testing.assert_allclose(got[1], slow[1], rtol=1e-15, atol=1e-15)


def test_session_rejections_carry_their_reason():
    session = Session()
    pose = Pose.identity()
    assert session.add_link_pose(10 * MS, pose) == []
    (duplicate,) = session.add_link_pose(10 * MS, pose)
    (late,) = session.add_link_pose(5 * MS, pose)
    (nan,) = session.add_sensor_pose(10 * MS, Pose(np.full(3, np.nan), quat.IDENTITY.copy()))
    assert [mc.rejected_reason(e) for e in (duplicate, late, nan)] == [
        'duplicate_stamp', 'out_of_order', 'non_finite']
    assert mc.rejected_reason(Rejected('link_pose', 'why')) == 'malformed'


def test_pairing_notice_waits_for_known_rates():
    # Found by test_fuzz: stamps jumping ahead and back leave a stream with too few poses
    # for a rate when the first pair forms; the notice used to fail formatting None. (The
    # link's jump back at 40 ms confirms the sensor's at 15 ms: a new timeline from there.)
    # It now waits until both streams' rates are known, and is said once.
    session = Session()
    events = []
    for stream, stamp_ms in (('l', 0), ('l', 10), ('s', 3002), ('s', 15), ('l', 3004),
                             ('l', 40), ('s', 50), ('l', 60), ('l', 70), ('s', 3008)):
        add = session.add_link_pose if stream == 'l' else session.add_sensor_pose
        events += add(stamp_ms * MS, Pose.identity())
    assert not any(isinstance(e, Notice) and 'pairing by' in e.text for e in events)
    for stamp_ms in range(3010, 4200, 10):   # link 100 Hz, sensor 25 Hz
        events += session.add_link_pose(stamp_ms * MS, Pose.identity())
        if stamp_ms % 40 == 0:
            events += session.add_sensor_pose((stamp_ms - 2) * MS, Pose.identity())
    said = [e.text for e in events if isinstance(e, Notice) and 'pairing by' in e.text]
    assert said == ['pairing by header stamps: link poses (100 Hz) interpolated at the sensor '
                    'stamps (25 Hz)']


def test_stream_stats_count_and_throttle():
    stats = mc.StreamStats(throttle_s=5.0)
    t = 1_000 * NS
    # The first message of a (stream, reason) is reported at once, then once per 5 s with
    # the number since the previous report.
    assert stats.note_bad(mc.SENSOR, 'non_finite', t) == 1
    assert [stats.note_bad(mc.SENSOR, 'non_finite', t + k * MS) for k in range(1, 100)] == \
        [None] * 99
    assert stats.note_bad(mc.SENSOR, 'zero_stamp', t + 100 * MS) == 1    # another reason
    assert stats.note_bad(mc.LINK, 'non_finite', t + 100 * MS) == 1      # another stream
    assert stats.note_bad(mc.SENSOR, 'non_finite', t + 5 * NS) == 100
    assert stats.note_bad(mc.SENSOR, 'non_finite', t + 6 * NS) is None
    assert stats.bad[mc.SENSOR, 'non_finite'] == 102
    assert stats.bad_total == 104
    assert stats.bad_of(mc.SENSOR) == 103


def test_stale_streams_are_named():
    stats = mc.StreamStats()
    t0 = 1_000 * NS
    assert stats.stale_reasons(t0 + 100 * NS) == []        # nothing received yet
    stats.note(mc.LINK, t0)
    stats.note_good(mc.LINK, t0)
    assert stats.stale_reasons(t0 + 2 * NS) == []
    assert stats.stale_reasons(t0 + 4 * NS) == [
        (mc.LINK, 'link_pose stale: no message for 4.0 s'),
        (mc.SENSOR, 'sensor_pose stale: no message at all in 4.0 s')]
    # The topic where its name is not the stream's: images (it said sensor_pose alone).
    assert stats.stale_reasons(t0 + 4 * NS, names={mc.LINK: '/link_pose',
                                                   mc.SENSOR: '/camera/image_raw'}) == [
        (mc.LINK, 'link_pose stale: no message for 4.0 s'),
        (mc.SENSOR, 'sensor_pose stale: no message on /camera/image_raw at all in 4.0 s')]
    stats.note(mc.LINK, t0 + 4 * NS)
    stats.note_good(mc.LINK, t0 + 4 * NS)
    stats.note(mc.SENSOR, t0 + int(0.2 * NS))
    stats.note_good(mc.SENSOR, t0 + int(0.2 * NS))
    assert stats.stale(t0 + int(4.4 * NS)) == [mc.SENSOR]
    assert stats.stale_reasons(t0 + int(4.4 * NS))[0][1] == \
        'sensor_pose stale: no message for 4.2 s'
    # A stream that sends only bad messages is stale too, and says why.
    for k in range(50):
        stats.note(mc.SENSOR, t0 + 4 * NS + k * 10 * MS)
        stats.note_bad(mc.SENSOR, 'non_finite', k)
    ((stream, text),) = stats.stale_reasons(t0 + int(4.4 * NS))
    assert stream == mc.SENSOR
    assert text == ('sensor_pose stale: no usable message for 4.2 s (bad messages only, '
                    'latest: NaN or inf in the pose)')


# --- the node --------------------------------------------------------------------------------

class Harness(SpinMixin):
    """A calibrator node and a driver node in one private context and executor."""

    spin_step = 0.02

    def __init__(self, domain_id, overrides=()):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.node = CalibratorNode(context=self.context, parameter_overrides=list(overrides))
        self.driver = rclpy.create_node('checks_driver', context=self.context)
        self.pubs = {stream: self.driver.create_publisher(PoseStamped, stream, RELIABLE)
                     for stream in mc.STREAMS}
        self.clock_pub = self.driver.create_publisher(Clock, '/clock', 10)
        self.diagnostics = []
        self.driver.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda msg: self.diagnostics.extend(
                s for s in msg.status if s.name == DIAGNOSTIC_NAME), 10)
        self.sent = dict.fromkeys(mc.STREAMS, 0)
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(lambda: all(p.get_subscription_count() for p in self.pubs.values()),
                        what='discovery')

    def publish(self, stream, msg):
        self.pubs[stream].publish(msg)
        self.sent[stream] += 1

    def publish_pose(self, stream, stamp_ns, pose, frame_id=''):
        self.publish(stream, conversions.pose_stamped_msg(pose, stamp_ns, frame_id))

    def wait_received(self):
        received = self.node.stats.received
        self.spin_until(lambda: all(received[s] >= self.sent[s] for s in mc.STREAMS),
                        what='the node to receive every message')

    def fresh_status(self):
        """Wait for the next /diagnostics status; return it and its values."""
        self.diagnostics.clear()
        self.spin_until(lambda: self.diagnostics, what='a /diagnostics status')
        status = self.diagnostics[-1]
        return status, {kv.key: kv.value for kv in status.values}

    def consistent(self):
        """Every message received was counted once, as good or as bad."""
        stats = self.node.stats
        for stream in mc.STREAMS:
            assert stats.received[stream] == stats.good[stream] + stats.bad_of(stream)


@pytest.fixture
def harness_factory(domain_id):
    made = []

    def make(overrides=()):
        made.append(Harness(domain_id, overrides))
        return made[-1]
    yield make
    for harness in made:
        harness.close()


def still_stream(cell, link, start_ns, duration_s=0.8, rate_hz=25.0, frames=('', '')):
    """Both streams at rate_hz holding one link pose (noise-free sensor): (stream, msg)."""
    sensor = cell.sensor_pose(link)
    out = []
    for i in range(int(duration_s * rate_hz)):
        stamp = start_ns + int(i * NS / rate_hz)
        out += [(mc.LINK, conversions.pose_stamped_msg(link, stamp, frames[0])),
                (mc.SENSOR, conversions.pose_stamped_msg(sensor, stamp, frames[1]))]
    return out


def test_every_kind_of_bad_message_is_counted_logged_and_skipped(harness_factory, capfd):
    h = harness_factory([Parameter('link_frame_id', value='base'),
                         Parameter('sensor_frame_id', value='camera'),
                         Parameter('diagnostics_period_s', value=0.2)])
    now = h.node.now_ns()
    t0 = now - 3 * NS
    identity = Pose.identity()

    def numbers(stamp_ns, position=(0.0, 0.0, 0.0), xyzw=(0.0, 0.0, 0.0, 1.0)):
        sec, nanosec = divmod(stamp_ns, NS)
        return _msg(position, xyzw, sec, nanosec, 'base')

    bad = {   # reason: link_pose message
        'duplicate_stamp': conversions.pose_stamped_msg(identity, t0, 'base'),
        'out_of_order': conversions.pose_stamped_msg(identity, t0 - 5 * MS, 'base'),
        'zero_stamp': conversions.pose_stamped_msg(identity, 0, 'base'),
        'stamp_in_future': conversions.pose_stamped_msg(identity, now + 60 * NS, 'base'),
        'stamp_in_past': conversions.pose_stamped_msg(identity, now - 60 * NS, 'base'),
        'wrong_frame_id': conversions.pose_stamped_msg(identity, t0 + MS, 'world'),
        'non_finite': numbers(t0 + 2 * MS, position=(0.0, float('nan'), 0.0)),
        'zero_quaternion': numbers(t0 + 3 * MS, xyzw=(0.0, 0.0, 0.0, 0.0)),
        'non_unit_quaternion': numbers(t0 + 4 * MS, xyzw=(0.0, 0.0, 0.0, 1.5)),
        'bad_stamp': _msg(sec=t0 // NS, nanosec=1_500_000_000, frame_id='base'),
    }
    h.publish(mc.LINK, conversions.pose_stamped_msg(identity, t0, 'base'))   # good
    for msg in bad.values():
        h.publish(mc.LINK, msg)
    # Slightly off the unit norm: renormalised and used.
    h.publish(mc.LINK, numbers(t0 + 6 * MS, xyzw=(0.0, 0.0, 0.0, 1.0005)))
    h.wait_received()
    stats = h.node.stats
    assert dict(stats.bad) == {(mc.LINK, reason): 1 for reason in bad}
    assert stats.good[mc.LINK] == 2
    h.consistent()
    status, values = h.fresh_status()
    for reason in bad:
        assert values[f'bad_link_pose_{reason}'] == '1', reason
    assert values['bad_messages'] == str(len(bad))
    assert values['link_messages'] == str(len(bad) + 2)
    # One warning per reason, naming the topic and the reason.
    logged = capfd.readouterr().err
    for reason in bad:
        assert len(re.findall(rf'/link_pose: bad message skipped \({reason}, 1 so far',
                              logged)) == 1, (reason, logged)
    assert "header.frame_id 'world' is not 'base' (parameter link_frame_id)" in logged

    # Good data afterwards is used: a still sample.
    cell = simulation.random_cell(np.random.default_rng(4))
    for stream, msg in still_stream(cell, cell.home, t0 + 10 * MS, frames=('base', 'camera')):
        h.publish(stream, msg)
    h.wait_received()
    h.spin_until(lambda: len(h.node.session.samples) == 1, what='a sample after bad input')
    assert stats.bad_total == len(bad)
    h.consistent()


def test_logs_are_throttled_per_stream_and_reason(harness_factory, capfd):
    h = harness_factory()
    now = h.node.now_ns()
    nan_pose = Pose(np.array([np.nan, 0.0, 0.0]), quat.IDENTITY.copy())
    started = time.monotonic()
    for k in range(300):
        msg = conversions.pose_stamped_msg(Pose.identity(), now + k * MS, '')
        msg.pose.position.x = nan_pose.position[0]
        h.publish(mc.SENSOR, msg)
        h.publish(mc.LINK, conversions.pose_stamped_msg(Pose.identity(), 0, ''))
        if k % 50 == 49:   # the sensor subscription is best effort, depth 100
            h.wait_received()
    stats = h.node.stats
    assert stats.bad[mc.SENSOR, 'non_finite'] == 300
    assert stats.bad[mc.LINK, 'zero_stamp'] == 300
    h.consistent()
    # One line per stream and reason, and one more per LOG_THROTTLE_S (steady clock) should
    # this loaded machine take that long: not one per message.
    most = 1 + int((time.monotonic() - started) // LOG_THROTTLE_S)
    logged = capfd.readouterr().err
    assert 1 <= logged.count('/sensor_pose: bad message skipped (non_finite') <= most
    assert 1 <= logged.count('/link_pose: bad message skipped (zero_stamp') <= most
    status, values = h.fresh_status()
    assert values['bad_sensor_pose_non_finite'] == '300'
    assert status.message.startswith('waiting for poses (600 bad messages skipped')


def test_sim_time_clock_checks_and_stale_stream(harness_factory):
    # With use_sim_time the node clock is /clock: stamps are checked against it, and a
    # stream is stale when /clock has run on without it.
    h = harness_factory([Parameter('use_sim_time', value=True),
                         Parameter('max_stamp_offset_s', value=10.0),
                         Parameter('diagnostics_period_s', value=0.1)])
    start = 500 * NS     # a bag recorded long ago

    def set_clock(ns):
        sec, nanosec = divmod(ns, NS)
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = sec, nanosec
        h.clock_pub.publish(msg)
        h.spin_until(lambda: h.node.now_ns() == ns, what='the node clock to follow /clock')

    set_clock(start)
    cell = simulation.random_cell(np.random.default_rng(9))
    for stream, msg in still_stream(cell, cell.home, start - NS):
        h.publish(stream, msg)
    h.publish_pose(mc.SENSOR, start + 20 * NS, cell.sensor_pose(cell.home))    # future
    h.wait_received()
    assert h.node.stats.bad == {(mc.SENSOR, 'stamp_in_future'): 1}
    h.spin_until(lambda: len(h.node.session.samples) == 1, what='a sample at sim time')

    # /clock runs on 4.2 s; only the link stream goes on.
    set_clock(start + int(4.2 * NS))
    h.publish_pose(mc.LINK, start + 4 * NS, cell.home)
    h.wait_received()
    # The diagnostics timer runs on the simulated clock too: build the status directly.
    status = h.node.diagnostic_status()
    values = {kv.key: kv.value for kv in status.values}
    assert values['stale'] == 'sensor_pose'
    assert status.level == status.WARN
    assert 'sensor_pose stale: no message for 4.2 s' in status.message
    h.consistent()


def test_frame_and_offset_parameters_change_at_runtime(harness_factory):
    h = harness_factory()
    node = h.node
    result = node.set_parameters_atomically([Parameter('sensor_frame_id', value='camera'),
                                             Parameter('max_stamp_offset_s', value=0.0)])
    assert result.successful
    assert node.checks == mc.CheckConfig(max_stamp_offset_ns=0, sensor_frame_id='camera')
    for parameter, words in ((Parameter('max_stamp_offset_s', value=-1.0), 'out of range'),
                             (Parameter('link_frame_id', value='  '), 'empty')):
        (result,) = node.set_parameters([parameter])
        assert not result.successful and words in result.reason, result.reason
    assert node.checks.max_stamp_offset_ns == 0
    h.publish_pose(mc.SENSOR, 5 * NS, Pose.identity(), 'camera_optical')
    h.publish_pose(mc.SENSOR, 6 * NS, Pose.identity(), 'camera')
    h.wait_received()
    assert dict(node.stats.bad) == {(mc.SENSOR, 'wrong_frame_id'): 1}


def test_a_stream_that_never_sent_anything_is_named_with_its_topic():
    stats = mc.StreamStats()
    t0 = 1_000 * NS
    names = {mc.LINK: '/robot/tool0_pose', mc.SENSOR: '/aruco/marker_pose'}
    assert stats.stale_reasons(t0 + 2 * NS, started_ns=t0, names=names) == []
    reasons = dict(stats.stale_reasons(t0 + 4 * NS, started_ns=t0, names=names))
    assert reasons[mc.LINK] == ('no message on /robot/tool0_pose yet: is it remapped to the '
                                'right topic, and does the publisher run?')
    assert '/aruco/marker_pose' in reasons[mc.SENSOR]
    stats.note(mc.SENSOR, t0 + 5 * NS)
    # From the first message on, the usual rule: the silent stream is stale after 3 s.
    assert stats.stale_reasons(t0 + 6 * NS, started_ns=t0, names=names) == []


def test_a_silent_input_is_named_by_its_topics_once():
    """Pose topics by their resolved names; TF input (both streams on /tf) named once."""
    from quatcal_ros.ros.diagnostics import calibrator_status
    from quatcal_ros.stream.session import Session, SessionConfig
    t0 = 1_000 * NS
    for topics, nothing in (({mc.LINK: '/robot/tool0_pose', mc.SENSOR: '/sensor_pose'},
                             '/robot/tool0_pose and /sensor_pose'),
                            ({mc.LINK: '/tf', mc.SENSOR: '/tf'}, None)):
        composed = {s for s, topic in topics.items() if topic == '/tf'}
        status = calibrator_status(Session(SessionConfig()), mc.StreamStats(), t0 + 4 * NS,
                                   'tool0', started_ns=t0, topics=topics, composed=composed)
        parts = status.message.split('; ')
        if nothing:
            assert parts[0] == f'waiting for poses (nothing on {nothing} yet)'
        else:   # TF input: /tf may be busy with other frames; it is not said to be silent
            assert parts[0] == ('waiting for poses (no link_pose or sensor_pose composed from '
                                '/tf yet)')
            assert parts[1].startswith('no pose composed from /tf yet: are the frame names')
        assert len(parts) == len(set(topics.values())) + 1


def test_streams_that_stopped_before_a_reset_are_not_blamed_on_the_clock():
    """After ~/reset the node's stats still hold both streams; the new session has nothing."""
    from quatcal_ros.ros.diagnostics import status_message
    from quatcal_ros.stream.session import Session, SessionConfig
    stats = mc.StreamStats()
    stats.note(mc.LINK, 1_000 * NS)
    stats.note(mc.SENSOR, 1_000 * NS)
    topics = {mc.LINK: '/robot/tool0_pose', mc.SENSOR: '/sensor_pose'}
    session = Session(SessionConfig())
    assert status_message(session, stats, topics) == (
        'waiting for poses (no pose from /robot/tool0_pose or /sensor_pose since the session '
        'started)')
    session.add_link_pose(1_000 * NS, Pose.identity())
    assert status_message(session, stats, topics) == (
        'waiting for poses (no pose from /sensor_pose since the session started)')
    session.add_sensor_pose(1_000 * NS + 7 * MS, Pose.identity())
    assert status_message(session, stats, topics) == (
        'waiting for poses (none paired yet: are both stamped on the same clock?)')


def test_a_robot_that_never_stops_is_told_to_stop_not_to_move_more():
    # Paired poses of a link turning all the time: the status asked for motions about two
    # axes, and nothing said that no window was ever still.
    from quatcal_ros.ros.diagnostics import status_message
    from quatcal_ros.stream.session import Session, SessionConfig
    session = Session(SessionConfig())
    for k in range(300):   # 3 s at 100 Hz, 20 deg/s
        turned = Pose.create([0.4, 0.0, 0.3], quat.from_axis_angle([0, 0, 1.0], 0.0035 * k))
        session.add_link_pose(1_000 * NS + k * 10 * MS, turned)
        if k % 3 == 0:
            session.add_sensor_pose(1_000 * NS + k * 10 * MS, Pose.identity())
    pairs = session.counters['pairs']
    assert pairs > 50 and not session.samples
    # The first seconds of a motion: stopping is what to do (continuous capture was offered
    # from the first second on).
    assert status_message(session, mc.StreamStats(), {}) == (
        f'collecting: no still sample yet from {pairs} paired poses: stop the robot at each '
        'pose for 0.5 s (still_window_s) after each motion')
    # For 30 s of stamps that is only the state; from then on a problem (WARN).
    from diagnostic_msgs.msg import DiagnosticStatus
    from quatcal_ros.ros.diagnostics import calibrator_status, NEVER_STILL_S
    for k in range(300, 3_100):   # to 31 s
        turned = Pose.create([0.4, 0.0, 0.3], quat.from_axis_angle([0, 0, 1.0], 0.0035 * k))
        session.add_link_pose(1_000 * NS + k * 10 * MS, turned)
        if k % 3 == 0:
            session.add_sensor_pose(1_000 * NS + k * 10 * MS, Pose.identity())
        if k == 1_100:   # 11 s: a robot that has not stopped may be one that never does
            assert status_message(session, mc.StreamStats(), {}).endswith(
                'after each motion; a robot that never stops needs capture_mode continuous')
        if k == 2_990:
            assert session.paired_seconds < NEVER_STILL_S
            status = calibrator_status(session, mc.StreamStats(), 0, 'tool0')
            assert status.level == DiagnosticStatus.OK, status.message
    status = calibrator_status(session, mc.StreamStats(), 0, 'tool0')
    assert status.level == DiagnosticStatus.WARN
    assert status.message.endswith('capture_mode continuous; no still sample in 31 s of '
                                   'paired poses')


def test_a_sensor_that_scatters_while_the_link_stands_still_is_named_with_its_bands():
    # The robot stops, but the detections scatter by 2 deg, beyond the sensor's 1 deg band:
    # the status names the parameters that widen it (the replay's error, its options).
    # With the bands it suggests, the same poses give a still sample.
    from quatcal_ros.ros.diagnostics import status_message
    from quatcal_ros.stream.capture import CaptureConfig
    from quatcal_ros.stream.session import Session, SessionConfig

    def stop(capture=CaptureConfig()):
        session = Session(SessionConfig(capture=capture))
        rng = np.random.default_rng(5)
        for k in range(120):   # 1.2 s at 100 Hz, the link still
            session.add_link_pose(1_000 * NS + k * 10 * MS, Pose.create([0.4, 0.0, 0.3],
                                                                        [1.0, 0.0, 0.0, 0.0]))
            if k % 3 == 0:
                scattered = quat.from_rotation_vector(np.radians(rng.normal(0.0, 2.0, 3)))
                session.add_sensor_pose(1_000 * NS + k * 10 * MS, Pose.create([0, 0, 1.0],
                                                                              scattered))
        return session
    session = stop()
    unsteady = session.counters['unsteady_sensor']
    assert unsteady > 0 and not session.samples
    degrees, metres = session.sensor_scatter
    assert 5.0 < degrees < 8.0 and metres == 0.005   # (the position does not scatter)
    assert status_message(session, mc.StreamStats(), {}).endswith(
        f'after each motion; at {unsteady} paired poses the link stood still but the sensor '
        'pose moved beyond its bands (1 deg, 0.005 m): for a sensor that noisy widen them '
        f'(sensor_still_rotation_deg {degrees:g}, sensor_still_translation_m 0.005: what the '
        'scatter seen there takes)')
    assert len(stop(CaptureConfig(sensor_rotation_band_deg=degrees)).samples) == 1
    # Not far beyond what it takes: 1.3-1.7 times the narrowest band that takes a sample
    # (measured on ten draws), so one 1.8 times narrower takes none.
    assert not stop(CaptureConfig(sensor_rotation_band_deg=degrees / 1.8)).samples


def test_the_node_logs_a_sensor_too_noisy_for_its_bands_once_it_is_a_problem(
        harness_factory):
    """/diagnostics alone said it: the log stayed silent for a minute of a noisy detector."""
    node = harness_factory().node
    rng = np.random.default_rng(5)
    with logged_warnings(node) as warned:
        for k in range(3_200):   # 32 s at 100 Hz, the link still, the detector scattering
            node.session.add_link_pose(1_000 * NS + k * 10 * MS, Pose.create(
                [0.4, 0.0, 0.3], [1.0, 0.0, 0.0, 0.0]))
            if k % 3 == 0:
                scattered = quat.from_rotation_vector(np.radians(rng.normal(0.0, 2.0, 3)))
                node.session.add_sensor_pose(1_000 * NS + k * 10 * MS,
                                             Pose.create([0, 0, 1.0], scattered))
            if k in (2_900, 3_100, 3_199):
                node.diagnostic_status()
    # Once, when it became a problem (31 s), not at 29 s, not again at 32 s.
    (text,) = warned
    assert re.fullmatch(
        r'no still sample in 31 s of paired poses: stop the robot at each pose for 0.5 s '
        r'\(still_window_s\) after each motion; at \d+ paired poses the link stood still but '
        r'the sensor pose moved beyond its bands \(1 deg, 0.005 m\): for a sensor that noisy '
        r'widen them \(sensor_still_rotation_deg [5-7]\.\d, sensor_still_translation_m '
        r'0.005: what the scatter seen there takes\)', text), text   # (the robot stops)


def test_a_pause_of_the_streams_is_not_paired_time():
    # 20 s of a turning link, 60 s without poses (the marker out of view), 5 s more: 25 s of
    # paired poses, not 85 (the WARN came at once after the pause). Steps of up to 5 s count.
    from quatcal_ros.stream.session import Session, SessionConfig
    session = Session(SessionConfig())
    for k in [*range(2_000), *range(8_000, 8_500)]:   # 100 Hz
        turned = Pose.create([0.4, 0.0, 0.3], quat.from_axis_angle([0, 0, 1.0], 0.0035 * k))
        session.add_link_pose(1_000 * NS + k * 10 * MS, turned)
        if k % 3 == 0:
            session.add_sensor_pose(1_000 * NS + k * 10 * MS, Pose.identity())
    assert 24.9 < session.paired_seconds < 25.0


def test_tf_input_with_one_pair_of_frames_composing_names_the_other():
    """/tf is busy (the link poses compose); the sensor's frames do not: not 'nothing on /tf'."""
    from quatcal_ros.ros.diagnostics import status_message
    from quatcal_ros.stream.session import Session, SessionConfig
    stats = mc.StreamStats()
    stats.note(mc.LINK, 1_000 * NS)
    message = status_message(Session(SessionConfig()), stats, {mc.LINK: '/tf', mc.SENSOR: '/tf'},
                             composed={mc.LINK, mc.SENSOR})
    assert message == 'waiting for poses (no sensor_pose composed from /tf yet)'


def test_tf_input_on_a_busy_tf_whose_frames_never_compose_says_so():
    """/tf carries other frames (a robot driver): the streams are not 'no message at all'."""
    from quatcal_ros.ros.diagnostics import calibrator_status
    from quatcal_ros.stream.session import Session, SessionConfig
    t0 = 1_000 * NS
    topics = {mc.LINK: '/tf', mc.SENSOR: '/tf'}
    stats = mc.StreamStats()
    for k in range(50):
        stats.note('/tf', t0 + k * 100 * MS)      # the node counts /tf's own messages
    status = calibrator_status(Session(SessionConfig()), stats, t0 + 5 * NS, 'tool0',
                               started_ns=t0, topics=topics, composed=set(topics))
    parts = status.message.split('; ')
    assert parts[0] == 'waiting for poses (no link_pose or sensor_pose composed from /tf yet)'
    assert parts[1:] == ['link_pose stale: no pose composed from /tf in 5.0 s',
                         'sensor_pose stale: no pose composed from /tf in 5.0 s']


def test_images_with_tf_for_the_link_name_each_input_as_it_is():
    """Camera images for the sensor, TF frames for the link: neither named as the other."""
    from quatcal_ros.ros.diagnostics import calibrator_status
    from quatcal_ros.stream.session import Session, SessionConfig
    t0 = 1_000 * NS
    topics = {mc.LINK: '/tf', mc.SENSOR: '/camera/image_raw'}
    status = calibrator_status(Session(SessionConfig()), mc.StreamStats(), t0 + 4 * NS, 'tool0',
                               started_ns=t0, topics=topics, composed={mc.LINK})
    parts = status.message.split('; ')
    assert parts[0] == ('waiting for poses (no link_pose composed from /tf yet, and nothing on '
                        '/camera/image_raw yet)')
    assert parts[1].startswith('no pose composed from /tf yet: are the frame names right')
    assert parts[2].startswith('no message on /camera/image_raw yet: is it remapped')


def test_publication_sequence_gaps_count_lost_messages():
    stats = mc.StreamStats()
    assert mc.LINK not in stats.lost   # not counted ('' on /diagnostics)
    stats.restart_sequence(mc.LINK)   # the stream has one publisher: counted from now on
    assert stats.lost == {mc.LINK: 0}
    for sequence in (7, 8, 11, 12, 20):   # the first number seen starts the count
        stats.note_sequence(mc.LINK, sequence)
    assert stats.lost[mc.LINK] == 2 + 7 and stats.lost[mc.SENSOR] == 0
    # Numbers that go back (a publisher restarted, or a second one's interleave: 3, 1, 4, 2)
    # stop the count until the publishers are checked again: no gap is made up.
    for sequence in (21, 3, 50_000, 4, 50_001, 5):
        stats.note_sequence(mc.LINK, sequence)
    assert stats.lost[mc.LINK] == 9
    stats.restart_sequence(mc.LINK, always=False)   # stopped: restarted
    for sequence in (6, 9):
        stats.note_sequence(mc.LINK, sequence)
    assert stats.lost[mc.LINK] == 11
    stats.restart_sequence(mc.LINK, always=False)   # counting: kept
    stats.note_sequence(mc.LINK, 12)
    assert stats.lost[mc.LINK] == 13
    # With the publisher's stamps: 1,500 lost in 1.5 s is a loss (1 kHz); a second publisher
    # discovered late, numbered 360,000 a millisecond later, is not: the count stops.
    stats.note_sequence(mc.LINK, 13, 10 * NS)
    stats.note_sequence(mc.LINK, 1_514, 10 * NS + 1_500 * MS)
    assert stats.lost[mc.LINK] == 13 + 1_500
    stats.note_sequence(mc.LINK, 360_000, 10 * NS + 1_501 * MS)
    stats.note_sequence(mc.LINK, 360_500, 10 * NS + 2_000 * MS)
    assert stats.lost[mc.LINK] == 1_513


def test_the_clocks_offset_is_read_from_the_arrival_times():
    from quatcal_ros.stream.arrival_lag import ArrivalLag, problem
    lags = ArrivalLag()
    lags.note(mc.LINK, 100 * NS, 0)   # use_sim_time before /clock: no arrival time (it gave
    lags.note(mc.SENSOR, 99 * NS, 0)  # a lag of minus the stamp)
    lags.end_period()
    assert lags.offset_ns() is None
    lags.note(mc.LINK, 100 * NS, 100 * NS + 2 * MS)
    assert lags.offset_ns() is None   # (until a period ends with both streams in it)
    lags.note(mc.SENSOR, 97 * NS, 100 * NS + 40 * MS)   # a camera 3 s behind, 40 ms late
    lags.note(mc.SENSOR, 97 * NS + 30 * MS, 100 * NS + 65 * MS)   # the shortest latency: 35
    lags.end_period()
    assert lags.offset_ns() == 3 * NS + 33 * MS
    assert problem(lags.offset_ns()).startswith(
        'the sensor stamps run 3.03 s behind the link stamps, against the times their poses '
        'arrive: the two clocks are not synchronised (synchronise them, e.g. with chrony, or '
        'set sensor_time_offset_s:=3.03, then call ~/reset')
    # With the offset set, what is left; within half a second nothing is said.
    assert lags.offset_ns(3 * NS) == 33 * MS and problem(lags.offset_ns(3 * NS), 3 * NS) is None
    assert 'with sensor_time_offset_s 1)' in problem(lags.offset_ns(NS), NS)
    assert 'sensor_time_offset_s:=3.03,' in problem(lags.offset_ns(NS), NS)
    # A later period without the sensor keeps its last lag; one ahead says so.
    lags.note(mc.LINK, 200 * NS, 200 * NS + 2 * MS)
    lags.note(mc.SENSOR, 202 * NS, 200 * NS + 40 * MS)
    lags.end_period()
    assert 'run 1.96 s ahead of the link stamps' in problem(lags.offset_ns())


def test_waiting_for_poses_says_why_the_first_bad_message_was_skipped():
    # 'most for no_board on sensor_pose' sent the user to the log for the hint (the markers
    # seen, and the board size to check).
    from quatcal_ros.ros.diagnostics import status_message
    from quatcal_ros.stream.session import Session
    stats = mc.StreamStats()
    for stream in mc.STREAMS:
        stats.note(stream, 0)
    stats.note_good(mc.LINK, 0)
    seen = '17 markers of DICT_5X5_100 seen: check squares_x and squares_y'
    for _ in range(3):
        stats.note_bad(mc.SENSOR, 'no_board', 0, seen)
    assert status_message(Session(), stats) == (
        'waiting for poses (3 bad messages skipped, most for no_board on sensor_pose, the '
        'first: 17 markers of DICT_5X5_100 seen: check squares_x and squares_y)')
    # The cause of today may not be the commonest: it said only the first, long fixed.
    stats.note_bad(mc.SENSOR, 'blurred', 0, 'sharpness 3 below 40')
    assert status_message(Session(), stats).endswith(
        'check squares_x and squares_y; the latest for blurred)')


def test_the_inputs_problems_come_before_the_estimates_warnings_on_diagnostics():
    # Swapped TF frames: the frame-convention warning advised another setup first, and the
    # swap (the cause) came last in a 1700-character status.
    from types import SimpleNamespace
    from quatcal_ros.ros.diagnostics import calibrator_status
    session = Session()
    result = SimpleNamespace(warnings=['frame convention: ... set setup to eye_to_hand'],
                             residual_rms_deg=0.1, validation={}, motions=3, inliers=3,
                             uncertainty_deg=0.1, method='refined', translation=[0, 0, 0],
                             translation_uncertainty_mm=1.0, hint='', reprojection=None)
    status = calibrator_status(session, mc.StreamStats(), 0, 'tool0',
                               problems=['TF input: the link frames look swapped'],
                               result=result)
    assert status.message.index('look swapped') < status.message.index('frame convention')


def test_an_estimates_log_line_gives_the_translation_too():
    # It gave the quaternion alone: the translation was on ~/transform and in the file only.
    from types import SimpleNamespace
    from quatcal_ros.ros.diagnostics import describe_result
    result = SimpleNamespace(quaternion=[1.0, 0.0, 0.0, 0.0], translation=[0.0099, -0.0106, 0.05],
                             residual_rms_deg=0.128, uncertainty_deg=0.036,
                             translation_uncertainty_mm=0.55, samples=11, inliers=55,
                             motions=55, hint='motions excite all axes', usable=True)
    line = describe_result(result)
    assert (', translation (0.0099, -0.0106, 0.0500) m, residual 0.128 deg RMS, uncertainty '
            '0.036 deg and 0.55 mm, from 11 samples (55 of 55 motions used); next: motions '
            'excite all axes') in line, line
    # One that says not to use it says so in its line too (~/transform carries it as well).
    result.usable = False
    assert describe_result(result).endswith(
        '(55 of 55 motions used); it says not to use it (usable false: its warnings); next: '
        'motions excite all axes')


def test_three_samples_leave_the_convention_unchecked_said_but_no_problem():
    # Every estimate from 3 samples says 'frame convention: not checked yet': the state of the
    # check, on /diagnostics with the level OK, logged as information (not a warning).
    from diagnostic_msgs.msg import DiagnosticStatus
    from quatcal_ros.ros.diagnostics import calibrator_status
    from quatcal_ros.ros.event_log import EventLog
    from quatcal_ros.stream.session import EstimateUpdated, SessionConfig
    rng = np.random.default_rng(2)
    samples, _ = simulation.samples(rng, simulation.random_cell(rng), 4, rotation_noise_deg=0.1)
    session = Session(SessionConfig())
    session.add_samples(samples[:3])
    session.estimate()
    assert session.result is not None
    status = calibrator_status(session, mc.StreamStats(), 0, 'tool0')
    assert status.level == DiagnosticStatus.OK, status.message
    assert '; frame convention: not checked yet: 3 samples fit every' in status.message
    from test_log_throttle import Lines   # (a logger that keeps its lines)
    logger = Lines()
    EventLog(logger).log([EstimateUpdated(session.result)], lambda result: [])
    assert ('info', session.result.warnings[0]) in logger.lines
    assert not [line for line in logger.lines if line[0] == 'warning']
    session.add_samples(samples[3:])
    session.estimate()
    assert 'not checked' not in calibrator_status(session, mc.StreamStats(), 0, 'tool0').message
