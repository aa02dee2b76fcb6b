"""Tests of quatcal_ros.stream.pairing: interpolation, gaps, bounded buffers, stamp order."""

import re

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from numpy.testing import assert_allclose
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.pairing import LINK, OutOfOrderStamp, Pairer, PairingConfig, SENSOR

START_NS = 1_700_000_000 * 10**9   # a realistic epoch: float64 cannot hold it to the ns
NS = 10**9


class ConstantTwist:
    """A pose moving at constant angular and linear velocity: SLERP and lerp are exact on it."""

    def __init__(self, rng, degrees_per_s, metres_per_s):
        self.q0 = quat.normalize(rng.standard_normal(4))
        self.p0 = rng.uniform(-1.0, 1.0, 3)
        axis = quat.normalize(rng.standard_normal(3))
        self.omega = axis * np.radians(degrees_per_s)
        self.velocity = quat.normalize(rng.standard_normal(3)) * metres_per_s

    def at(self, stamp_ns):
        t = (stamp_ns - START_NS) / NS
        q = quat.multiply(self.q0, quat.from_rotation_vector(self.omega * t))
        return Pose(self.p0 + self.velocity * t, q)


def stamps(rate_hz, duration_s, offset_ns=0):
    """Integer stamps from START_NS + offset_ns at rate_hz for duration_s."""
    count = int(duration_s * rate_hz)
    return [START_NS + offset_ns + int(round(i * NS / rate_hz)) for i in range(count)]


def feed(pairer, link, sensor):
    """Add (stamp, pose) lists in stamp order (link first on equal stamps); return all pairs."""
    messages = sorted([(s, 0, p) for s, p in link] + [(s, 1, p) for s, p in sensor],
                      key=lambda m: m[:2])
    pairs = []
    for stamp, kind, pose in messages:
        pairs += pairer.add(LINK, stamp, pose) if kind == 0 else pairer.add(SENSOR, stamp, pose)
    return pairs


def assert_same_pose(pose, expected, atol):
    assert_allclose(pose.position, expected.position, rtol=0.0, atol=atol)
    sign = 1.0 if pose.quaternion @ expected.quaternion >= 0.0 else -1.0
    assert_allclose(sign * pose.quaternion, expected.quaternion, rtol=0.0, atol=atol)


def marker(stamp_ns):
    """Make a sensor pose that encodes its own stamp, to check which one a pair uses."""
    return Pose(np.array([0.0, 0.0, (stamp_ns - START_NS) / NS]), quat.IDENTITY.copy())


def test_link_is_interpolated_at_sensor_stamps_exactly():
    rng = np.random.default_rng(1)
    link_truth = ConstantTwist(rng, degrees_per_s=90.0, metres_per_s=0.5)
    link = [(s, link_truth.at(s)) for s in stamps(500.0, 3.0)]
    # Sensor stamps 30 Hz, off the link grid by an odd number of nanoseconds.
    sensor = [(s, marker(s)) for s in stamps(30.0, 2.9, offset_ns=12_345_677)]
    pairer = Pairer()
    pairs = feed(pairer, link, sensor)
    assert pairer.faster == 'link'
    assert len(pairs) == len(sensor)
    for pair, (stamp, sensor_pose) in zip(pairs, sensor):
        assert pair.stamp_ns == stamp and pair.sensor is sensor_pose
        # 0.18 deg between link samples: quaternion.slerp takes its normalised-lerp branch
        # (dot > 0.9995), whose error there is ~1e-11; 1e-9 leaves room for rounding.
        assert_same_pose(pair.link, link_truth.at(stamp), atol=1e-9)


@pytest.mark.parametrize('sensor_hz, window_s', [(30.0, 2.0), (2.0, 2.0), (30.0, 0.4)])
def test_typical_rates_wait_for_a_span_and_ignore_a_lost_message(sensor_hz, window_s):
    # The subscription's second camera frame is lost: the mean rate of the first three kept
    # stamps read 20 Hz for a 30 Hz camera; the median interval reads 30 Hz. The rates wait
    # for four stamps spanning half a second (or half the window, when shorter).
    sensor_times = [t for k, t in enumerate(stamps(sensor_hz, 3.0)) if k != 1]
    pairer = Pairer(PairingConfig(window_ns=int(window_s * NS)))
    wait_ns = min(0.5, window_s / 2) * NS
    said = None
    for stamp, kind in sorted([(s, 0) for s in stamps(100.0, 3.0)] +
                              [(s, 1) for s in sensor_times]):
        pairer.add(LINK if kind == 0 else SENSOR, stamp, Pose.identity())
        rates = pairer.typical_rates_hz()
        if rates is not None and said is None:
            said = stamp
            # (the stamps are whole nanoseconds: 1 ns in 33 ms is 3e-8)
            assert rates == pytest.approx({LINK: 100.0, SENSOR: sensor_hz}, rel=1e-7)
        if stamp - START_NS < wait_ns - 10 * NS / 1000:
            assert rates is None
    assert said is not None and said - START_NS <= max(wait_ns, 4 / sensor_hz * NS) + 0.01 * NS


def test_faster_sensor_stream_is_interpolated_at_link_stamps():
    rng = np.random.default_rng(2)
    sensor_truth = ConstantTwist(rng, degrees_per_s=600.0, metres_per_s=0.2)
    link = [(s, marker(s)) for s in stamps(10.0, 3.0, offset_ns=3_000_001)]
    sensor = [(s, sensor_truth.at(s)) for s in stamps(60.0, 3.2)]
    pairer = Pairer()
    pairs = feed(pairer, link, sensor)
    assert pairer.faster == 'sensor'
    assert [pair.stamp_ns for pair in pairs] == [s for s, _ in link]
    for pair in pairs:
        # 10 deg between sensor samples: the true SLERP branch, exact up to rounding.
        assert_same_pose(pair.sensor, sensor_truth.at(pair.stamp_ns), atol=1e-12)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), link_hz=st.floats(20.0, 1000.0),
       sensor_hz=st.floats(5.0, 60.0), latency_ms=st.integers(0, 200))
def test_any_rates_and_latency_give_exact_pairs_in_order(seed, link_hz, sensor_hz, latency_ms):
    rng = np.random.default_rng(seed)
    link_truth = ConstantTwist(rng, 60.0, 0.3)
    sensor_truth = ConstantTwist(rng, 60.0, 0.3)
    link = [(s, link_truth.at(s)) for s in stamps(link_hz, 2.0) if rng.random() > 0.1]
    sensor = [(s, sensor_truth.at(s)) for s in stamps(sensor_hz, 2.0, int(rng.integers(NS)) // 10)
              if rng.random() > 0.1]
    # Delivery order: camera frames arrive latency_ms after their stamps.
    delivery = sorted([(s, 0, s, p) for s, p in link]
                      + [(s + latency_ms * 1_000_000, 1, s, p) for s, p in sensor])
    pairer = Pairer(PairingConfig(tolerance_ns=0))   # interpolated or exact stamps only
    pairs = []
    for _, kind, stamp, pose in delivery:
        pairs += pairer.add(LINK, stamp, pose) if kind == 0 else pairer.add(SENSOR, stamp, pose)
    slower = dict(sensor if pairer.faster == 'link' else link)
    assert all(a.stamp_ns < b.stamp_ns for a, b in zip(pairs, pairs[1:]))
    assert len(pairs) + sum(pairer.unpaired.values()) <= len(slower)
    for pair in pairs:
        assert pair.stamp_ns in slower
        # Up to 3.6 deg between neighbours quaternion.slerp normalises a lerp, off by at most
        # 5e-7 there; elsewhere it is exact to rounding.
        assert_same_pose(pair.link, link_truth.at(pair.stamp_ns), atol=1e-6)
        assert_same_pose(pair.sensor, sensor_truth.at(pair.stamp_ns), atol=1e-6)


def test_exact_stamps_pair_with_the_samples_themselves():
    rng = np.random.default_rng(3)
    truth = ConstantTwist(rng, 30.0, 0.1)
    common = stamps(30.0, 1.0)
    link = [(s, truth.at(s)) for s in common]
    sensor = [(s, marker(s)) for s in common]
    pairs = feed(Pairer(), link, sensor)
    assert len(pairs) == len(common)
    for pair, (_, link_pose), (_, sensor_pose) in zip(pairs, link, sensor):
        assert pair.link is link_pose and pair.sensor is sensor_pose


def test_nothing_is_paired_across_a_gap():
    rng = np.random.default_rng(4)
    truth = ConstantTwist(rng, 45.0, 0.2)
    gap = (START_NS + NS, START_NS + NS + 300_000_000)   # 0.3 s without link poses
    link = [(s, truth.at(s)) for s in stamps(500.0, 3.0) if not gap[0] < s < gap[1]]
    last_before_gap = max(s for s, _ in link if s <= gap[0])
    sensor_stamps = stamps(30.0, 2.9, offset_ns=1_234_567) + [last_before_gap + 400_000]
    sensor = [(s, marker(s)) for s in sorted(sensor_stamps)]
    config = PairingConfig(tolerance_ns=1_000_000, max_gap_ns=50_000_000)
    pairer = Pairer(config)
    pairs = feed(pairer, link, sensor)
    paired = {pair.stamp_ns: pair for pair in pairs}
    in_gap = [s for s in sensor_stamps if gap[0] < s < gap[1]]
    assert len(in_gap) == 10
    # Within tolerance (0.4 ms) of the last link pose before the gap: paired with it as it is.
    assert paired.pop(last_before_gap + 400_000).link is dict(link)[last_before_gap]
    assert not set(in_gap) & set(paired)
    assert pairer.unpaired['gap'] == len(in_gap) - 1
    assert 'gap of 0.300 s' in pairer.last_unpaired
    # stamps in seconds, as every other line gives them (one gave 1700000001150000000 ns)
    assert re.search(r'around sensor stamp 1700000001\.\d{3} s \(max gap', pairer.last_unpaired)
    for stamp, pair in paired.items():
        assert_same_pose(pair.link, truth.at(stamp), atol=1e-9)   # as in the exactness test


def test_a_late_sensor_frame_waits_for_the_link_to_reach_its_stamp():
    rng = np.random.default_rng(5)
    truth = ConstantTwist(rng, 20.0, 0.1)
    pairer = Pairer()
    link = [(s, truth.at(s)) for s in stamps(500.0, 0.2)]
    sensor = [(s, marker(s)) for s in stamps(30.0, 0.134, offset_ns=1_000)]   # 4 frames
    assert len(feed(pairer, link[:60], sensor)) == 4     # roles are known from here on
    early = START_NS + 150_000_777    # a sensor stamp ahead of the newest link pose (118 ms)
    assert pairer.add(SENSOR, early, marker(early)) == []
    pairs = []
    for stamp, pose in link[60:]:
        pairs += pairer.add(LINK, stamp, pose)
    assert [pair.stamp_ns for pair in pairs] == [early]
    assert_same_pose(pairs[0].link, truth.at(early), atol=1e-9)


def test_sensor_frames_are_dropped_when_the_link_stream_stops():
    config = PairingConfig(window_ns=500_000_000)
    pairer = Pairer(config)
    link = [(s, Pose.identity()) for s in stamps(500.0, 0.1)]
    sensor = [(s, marker(s)) for s in stamps(30.0, 2.0, offset_ns=1_000)]
    feed(pairer, link, sensor)
    assert pairer.unpaired['waiting'] > 0
    assert re.fullmatch(r'the link stream stopped at stamp 1700000000\.\d{3} s, \d\.\d{3} s '
                        r'before this sensor stamp', pairer.last_unpaired), pairer.last_unpaired
    assert pairer.buffered()['sensor'] <= 0.5 * 30 + 1


def test_buffers_are_bounded_by_window_and_length():
    config = PairingConfig(window_ns=NS, max_length=300)
    pairer = Pairer(config)
    link = [(s, Pose.identity()) for s in stamps(1000.0, 20.0)]
    sensor = [(s, marker(s)) for s in stamps(30.0, 20.0, offset_ns=333)]
    largest = {'link': 0, 'sensor': 0}
    messages = sorted([(s, 0, p) for s, p in link] + [(s, 1, p) for s, p in sensor],
                      key=lambda m: m[:2])
    for stamp, kind, pose in messages:
        pairer.add('link' if kind == 0 else 'sensor', stamp, pose)
        for name, count in pairer.buffered().items():
            largest[name] = max(largest[name], count)
    assert largest['link'] == 300          # max_length binds: 1 s at 1 kHz is 1001 poses
    assert 30 <= largest['sensor'] <= 31   # the window binds: 1 s at 30 Hz
    # The storage behind the buffers is compacted, not only the visible part.
    assert len(pairer._streams['link']._stamps) <= 2 * max(300, 256)


def test_out_of_order_stamps_are_reported_and_change_nothing():
    rng = np.random.default_rng(6)
    truth = ConstantTwist(rng, 30.0, 0.1)
    pairer = Pairer()
    link = [(s, truth.at(s)) for s in stamps(500.0, 0.5)]
    sensor = [(s, marker(s)) for s in stamps(30.0, 0.4, offset_ns=999)]
    before = len(feed(pairer, link, sensor))
    newest = link[-1][0]
    with pytest.raises(OutOfOrderStamp) as older:
        pairer.add(LINK, newest - 5_000_000, truth.at(newest))
    assert older.value.jump_ns == 5_000_000 and older.value.stream == 'link'
    with pytest.raises(OutOfOrderStamp) as repeated:
        pairer.add(SENSOR, sensor[-1][0], marker(sensor[-1][0]))
    assert repeated.value.jump_ns == 0
    # Unchanged: the next in-order messages pair as before.
    after = feed(pairer, [(s, truth.at(s)) for s in stamps(500.0, 0.1, offset_ns=NS)],
                 [(START_NS + NS + 50_000_001, marker(START_NS + NS + 50_000_001))])
    assert before == len(sensor) and len(after) == 1
    assert_same_pose(after[0].link, truth.at(after[0].stamp_ns), atol=1e-9)


def test_reset_starts_a_new_timeline_without_mixing_the_old_one():
    rng = np.random.default_rng(7)
    first, second = ConstantTwist(rng, 30.0, 0.1), ConstantTwist(rng, 30.0, 0.1)
    pairer = Pairer()
    feed(pairer, [(s, first.at(s)) for s in stamps(500.0, 2.0, offset_ns=10 * NS)],
         [(s, marker(s)) for s in stamps(30.0, 2.0, offset_ns=10 * NS + 7)])
    with pytest.raises(OutOfOrderStamp):
        pairer.add(LINK, START_NS, second.at(START_NS))
    pairer.reset()
    assert pairer.faster is None and pairer.buffered() == {'link': 0, 'sensor': 0}
    pairs = feed(pairer, [(s, second.at(s)) for s in stamps(500.0, 1.0)],
                 [(s, marker(s)) for s in stamps(30.0, 1.0, offset_ns=7)])
    assert len(pairs) == 30
    for pair in pairs:
        assert_same_pose(pair.link, second.at(pair.stamp_ns), atol=1e-9)


def test_config_is_checked():
    with pytest.raises(ValueError):
        PairingConfig(max_gap_ns=0)
    with pytest.raises(ValueError):
        PairingConfig(window_ns=10, max_gap_ns=100)


def delivered_runs(messages):
    """Split (stream, stamp, Pose) messages into runs of one stream: [(stream, [messages])]."""
    runs = []
    for message in messages:
        if runs and runs[-1][0] == message[0]:
            runs[-1][1].append(message)
        else:
            runs.append((message[0], [message]))
    return runs


def add_one_by_one(pairer, messages):
    """add() each (stream, stamp, Pose); return [(message index, Pair)] and the refused."""
    pairs, refused = [], []
    for index, (stream, stamp, pose) in enumerate(messages):
        try:
            pairs += [(index, pair) for pair in pairer.add(stream, stamp, pose)]
        except OutOfOrderStamp:
            refused.append(index)
    return pairs, refused


def add_in_runs(pairer, messages):
    """add_many() each run, add() what it does not take; as add_one_by_one returns."""
    pairs, refused, index = [], [], 0
    for stream, run in delivered_runs(messages):
        stamps_ns = [stamp for _, stamp, _ in run]
        positions = np.array([pose.position for _, _, pose in run])
        quaternions = np.array([pose.quaternion for _, _, pose in run])
        start = 0
        while start < len(run):
            taken, new = pairer.add_many(stream, stamps_ns[start:], positions[start:],
                                         quaternions[start:])
            if not taken:
                try:
                    new = pairer.add(stream, *run[start][1:])
                except OutOfOrderStamp:
                    refused.append(index + start)
                taken = 1
            pairs += [(index + start + taken - 1, pair) for pair in new]
            start += taken
        index += len(run)
    return pairs, refused


def assert_same_pairs(ours, theirs):
    assert [(index, pair.stamp_ns) for index, pair in ours] == \
        [(index, pair.stamp_ns) for index, pair in theirs]
    for (_, a), (_, b) in zip(ours, theirs):
        for pose, other in ((a.link, b.link), (a.sensor, b.sensor)):
            assert np.array_equal(pose.position, other.position)
            assert np.array_equal(pose.quaternion, other.quaternion)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), link_hz=st.floats(20.0, 1000.0),
       sensor_hz=st.floats(5.0, 200.0), latency_ms=st.integers(-50, 300),
       max_length=st.integers(20, 400), disorder=st.floats(0.0, 0.05))
def test_add_many_is_add_one_by_one(seed, link_hz, sensor_hz, latency_ms, max_length,
                                    disorder):
    """Runs of either stream, either faster, late or early, gaps, repeated and old stamps."""
    rng = np.random.default_rng(seed)
    truth = ConstantTwist(rng, 60.0, 0.3)
    link = [(s, truth.at(s)) for s in stamps(link_hz, 3.0) if rng.random() > 0.1]
    sensor = [(s, marker(s)) for s in stamps(sensor_hz, 3.0, int(rng.integers(NS)) // 10)
              if rng.random() > 0.1]
    delivery = sorted([(s, 0, 'link', s, p) for s, p in link]
                      + [(s + latency_ms * 1_000_000, 1, 'sensor', s, p) for s, p in sensor])
    messages = [(stream, stamp, pose) for _, _, stream, stamp, pose in delivery]
    for k in np.flatnonzero(rng.random(len(messages)) < disorder):   # repeats, old stamps
        stream, stamp, pose = messages[k]
        messages[k] = (stream, stamp - int(rng.integers(0, 2)) * 7_000_000 - 10, pose)
    config = PairingConfig(window_ns=NS // 2, max_length=max_length)
    one_by_one, in_runs = Pairer(config), Pairer(config)
    expected, refused = add_one_by_one(one_by_one, messages)
    pairs, refused_in_runs = add_in_runs(in_runs, messages)
    assert refused_in_runs == refused
    assert_same_pairs(pairs, expected)
    assert in_runs.faster == one_by_one.faster
    assert in_runs.buffered() == one_by_one.buffered()
    assert in_runs.rates_hz() == one_by_one.rates_hz()
    assert (in_runs.unpaired, in_runs.last_unpaired) == \
        (one_by_one.unpaired, one_by_one.last_unpaired)


def test_a_message_lost_early_does_not_choose_the_slower_stream_to_interpolate():
    # A 40 Hz link whose second pose is lost read 26.7 Hz by the mean of its first three
    # stamps, slower than a 30 Hz camera; the 1.5x hysteresis then kept that role.
    pairer = Pairer()
    link = [(s, Pose.identity()) for s in stamps(40.0, 1.0)]
    del link[1]
    feed(pairer, link, [(s, marker(s)) for s in stamps(30.0, 1.0, offset_ns=1_000)])
    assert pairer.faster == LINK
    assert pairer.rates_hz() == {LINK: pytest.approx(40.0), SENSOR: pytest.approx(30.0)}
    # A detector so slow that its window never keeps four frames still pairs (from three).
    pairer = Pairer()
    link = [(s, Pose.identity()) for s in stamps(500.0, 30.0)]
    pairs = feed(pairer, link, [(s, marker(s)) for s in stamps(0.5, 30.0, offset_ns=1_000)])
    # (all 15 but the first: the link poses at its stamp left the 2 s window before the
    # third frame decided)
    assert pairer.faster == LINK and len(pairs) == 14


def test_add_many_stops_at_the_pose_that_completes_pairs():
    pairer = Pairer()
    link = [(s, Pose.identity()) for s in stamps(1000.0, 0.11)]
    assert len(feed(pairer, link, [(s, marker(s)) for s in stamps(30.0, 0.134)])) == 4
    late = START_NS + 120_500_000   # a camera frame ahead of the link stream
    assert pairer.add(SENSOR, late, marker(late)) == []
    more = stamps(1000.0, 0.05, offset_ns=110_000_000)
    rows = np.zeros((len(more), 3)), np.tile(quat.IDENTITY, (len(more), 1))
    taken, pairs = pairer.add_many('link', more, *rows)
    assert more[taken - 2] < late <= more[taken - 1]
    assert [pair.stamp_ns for pair in pairs] == [late]
    assert pairer.add_many('link', more[taken:], *rows) == (len(more) - taken, [])
    assert pairer.add_many('sensor', [late + 1], *rows) == (0, [])     # the slower stream
    assert pairer.add_many('link', [more[-1]], *rows) == (0, [])       # not newer
