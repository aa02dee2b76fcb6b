"""Tests of quatcal_ros.stream.pose_buffer: order, lookup, interpolation, gaps, trimming."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from numpy.testing import assert_allclose
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.pose_buffer import (
    COMPACT_AFTER, GAP, interpolate_pose, LATER, Miss, OLDER, PoseBuffer, StampNotNewer)

START_NS = 1_700_000_000 * 10**9   # a realistic epoch: float64 cannot hold it to the ns
MS = 1_000_000


def marker(stamp_ns):
    """Make a pose that encodes its own stamp (x in ms from START_NS)."""
    return Pose(np.array([(stamp_ns - START_NS) / MS, 0.0, 0.0]), quat.IDENTITY.copy())


def filled(stamps_ms, **limits):
    buffer = PoseBuffer(**limits)
    for stamp_ms in stamps_ms:
        buffer.append(START_NS + stamp_ms * MS, marker(START_NS + stamp_ms * MS))
    return buffer


def kept(buffer):
    """Return the kept stamps in ms from START_NS."""
    return [(stamp - START_NS) // MS for stamp, _ in buffer.after()]


def assert_same_pose(pose, expected, atol):
    assert_allclose(pose.position, expected.position, rtol=0.0, atol=atol)
    sign = 1.0 if pose.quaternion @ expected.quaternion >= 0.0 else -1.0
    assert_allclose(sign * pose.quaternion, expected.quaternion, rtol=0.0, atol=atol)


def test_append_needs_newer_stamps_and_changes_nothing_otherwise():
    buffer = filled([0, 10, 20])
    for stamp_ms in (20, 5):
        with pytest.raises(StampNotNewer) as error:
            buffer.append(START_NS + stamp_ms * MS, Pose.identity())
        assert (error.value.stamp_ns, error.value.newest_ns) == \
            (START_NS + stamp_ms * MS, START_NS + 20 * MS)
    assert kept(buffer) == [0, 10, 20]
    assert (buffer.oldest_ns, buffer.newest_ns, buffer.span_ns) == \
        (START_NS, START_NS + 20 * MS, 20 * MS)


def test_empty_buffer():
    buffer = PoseBuffer()
    assert (len(buffer), buffer.oldest_ns, buffer.newest_ns, buffer.span_ns) == (0, None, None, 0)
    assert buffer.at(START_NS) == (None, Miss(LATER, None, None))
    assert buffer.first_after(START_NS) is None and buffer.last_at_or_before(START_NS) is None
    assert buffer.poses() == [] and list(buffer.after()) == []


def test_insert_keeps_order_replaces_equal_stamps_and_refuses_too_old_ones():
    buffer = PoseBuffer(window_ns=100 * MS)
    for stamp_ms in (50, 90, 70, 60):
        assert buffer.insert(START_NS + stamp_ms * MS, marker(START_NS + stamp_ms * MS))
    assert kept(buffer) == [50, 60, 70, 90]
    replacement = Pose.identity()
    assert buffer.insert(START_NS + 70 * MS, replacement)
    assert buffer.at(START_NS + 70 * MS)[0] is replacement and len(buffer) == 4
    assert buffer.insert(START_NS - 10 * MS, Pose.identity())       # within the window
    assert not buffer.insert(START_NS - 11 * MS, Pose.identity())   # older than it
    assert kept(buffer) == [-10, 50, 60, 70, 90]


def test_an_equal_stamp_gives_the_stored_pose_itself():
    buffer = filled([0, 10, 20])
    stored = dict(buffer.after())
    for stamp in stored:
        pose, miss = buffer.at(stamp, max_gap_ns=MS)
        assert miss is None and pose is stored[stamp]


def test_interpolate_pose_endpoints_and_midpoint():
    a = Pose.create([0.0, 0.0, 0.0], quat.IDENTITY)
    b = Pose.create([2.0, 0.0, 0.0], quat.from_axis_angle([0.0, 0.0, 1.0], np.radians(90.0)))
    assert_same_pose(interpolate_pose(a, b, 0.0), a, atol=1e-15)
    assert_same_pose(interpolate_pose(a, b, 1.0), b, atol=1e-15)
    middle = Pose.create([1.0, 0.0, 0.0],
                         quat.from_axis_angle([0.0, 0.0, 1.0], np.radians(45.0)))
    assert_same_pose(interpolate_pose(a, b, 0.5), middle, atol=1e-15)


def test_lookup_between_two_poses_is_lerp_and_slerp():
    rng = np.random.default_rng(4)
    q0 = quat.normalize(rng.standard_normal(4))
    omega = quat.normalize(rng.standard_normal(3)) * np.radians(30.0)   # rad per 10 ms
    p0, velocity = rng.standard_normal(3), rng.standard_normal(3)       # m per 10 ms
    buffer = PoseBuffer()
    for k in range(3):
        rotation = quat.multiply(q0, quat.from_rotation_vector(k * omega))
        buffer.append(START_NS + 10 * k * MS, Pose(p0 + k * velocity, rotation))
    for offset_ns in (1, 2_500_000, 7 * MS, 10 * MS - 1, 13 * MS, 19_999_999):
        pose, miss = buffer.at(START_NS + offset_ns, max_gap_ns=10 * MS)
        t = offset_ns / (10 * MS)
        k, fraction = int(t), t - int(t)
        before, after = (buffer.at(START_NS + 10 * j * MS)[0] for j in (k, k + 1))
        slerp = quat.slerp(before.quaternion, after.quaternion, fraction)
        assert miss is None
        lerp = before.position + fraction * (after.position - before.position)
        assert_same_pose(pose, Pose(lerp, slerp), atol=1e-15)
        # A constant angular and linear velocity is what SLERP and lerp reproduce exactly.
        truth = Pose(p0 + t * velocity, quat.multiply(q0, quat.from_rotation_vector(t * omega)))
        assert_same_pose(pose, truth, atol=1e-12)


def test_nothing_is_interpolated_across_a_gap_or_extrapolated():
    buffer = filled([0, 10, 100, 110])
    assert buffer.at(START_NS + 50 * MS, max_gap_ns=50 * MS) == \
        (None, Miss(GAP, START_NS + 10 * MS, START_NS + 100 * MS))
    assert buffer.at(START_NS + 50 * MS, max_gap_ns=90 * MS)[1] is None   # the gap is allowed
    assert buffer.at(START_NS + 50 * MS)[1] is None                        # no limit
    assert buffer.at(START_NS - 1, max_gap_ns=90 * MS) == (None, Miss(OLDER, None, START_NS))
    assert buffer.at(START_NS + 110 * MS + 1) == \
        (None, Miss(LATER, START_NS + 110 * MS, None))


def test_outside_a_bracket_the_nearer_pose_within_the_tolerance_is_used():
    buffer = filled([0, 10, 100, 110])
    at = dict(buffer.after())

    def near(offset_ns, tolerance_ns=2 * MS):
        return buffer.at(START_NS + offset_ns, max_gap_ns=50 * MS, tolerance_ns=tolerance_ns)

    assert near(12 * MS)[0] is at[START_NS + 10 * MS]
    assert near(98 * MS)[0] is at[START_NS + 100 * MS]
    assert near(12 * MS + 1)[1].reason == GAP
    assert near(-2 * MS)[0] is at[START_NS]            # older than the oldest, but near it
    assert near(-2 * MS - 1)[1].reason == OLDER
    assert near(55 * MS, tolerance_ns=45 * MS)[0] is at[START_NS + 100 * MS]   # tie: later
    assert buffer.at(START_NS + 110 * MS + 1, tolerance_ns=MS)[1].reason == LATER


def test_range_queries():
    buffer = filled([0, 10, 20, 30])
    assert buffer.first_after(START_NS + 10 * MS) == START_NS + 20 * MS
    assert buffer.first_after(START_NS + 30 * MS) is None
    assert buffer.last_at_or_before(START_NS + 10 * MS) == START_NS + 10 * MS
    assert buffer.last_at_or_before(START_NS + 19 * MS) == START_NS + 10 * MS
    assert buffer.last_at_or_before(START_NS - 1) is None
    assert [stamp for stamp, _ in buffer.after(START_NS + 15 * MS)] == \
        [START_NS + 20 * MS, START_NS + 30 * MS]
    assert [pose.position[0] for pose in buffer.poses()] == [0.0, 10.0, 20.0, 30.0]


def test_trim_by_window_and_length():
    by_window = filled(range(0, 200, 10), window_ns=50 * MS)
    by_window.trim()
    assert kept(by_window) == [140, 150, 160, 170, 180, 190]
    by_length = filled(range(0, 200, 10), max_length=3)
    by_length.trim()
    assert kept(by_length) == [170, 180, 190]
    both = filled(range(0, 200, 10), window_ns=50 * MS, max_length=4)
    both.trim()
    assert kept(both) == [160, 170, 180, 190]
    # What is forgotten is forgotten for lookups and range queries too.
    assert both.at(START_NS + 150 * MS)[1] == Miss(OLDER, None, START_NS + 160 * MS)
    assert both.last_at_or_before(START_NS + 155 * MS) is None
    assert both.span_ns == 30 * MS


def test_median_interval_of_the_kept_stamps_or_of_the_newest_ones():
    assert filled([0]).median_interval_ns() is None
    lost = filled([0, 20, 30, 40])     # one lost message: 20, 10, 10
    assert lost.median_interval_ns() == 10 * MS
    slowed = filled([0, 10, 20, 30, 40, 50, 70, 90])   # 10 ms five times, then 20 ms
    assert slowed.median_interval_ns() == 10 * MS
    assert slowed.median_interval_ns(recent=3) == 20 * MS
    assert slowed.median_interval_ns(recent=100) == 10 * MS
    slowed.forget_older_than(START_NS + 50 * MS)   # the kept ones only
    assert slowed.median_interval_ns() == 20 * MS


def test_forget_older_than():
    buffer = filled(range(0, 100, 10))
    buffer.forget_older_than(START_NS + 35 * MS)
    assert kept(buffer) == [40, 50, 60, 70, 80, 90]
    buffer.forget_older_than(START_NS + 40 * MS)
    assert len(buffer) == 6
    buffer.forget_older_than(START_NS + 91 * MS)
    assert (len(buffer), buffer.newest_ns) == (0, None)
    buffer.append(START_NS, marker(START_NS))   # empty again: any stamp is newer
    assert kept(buffer) == [0]


def test_storage_is_compacted_not_only_the_kept_part():
    buffer = PoseBuffer(max_length=10)
    for k in range(5000):
        buffer.append(START_NS + k * MS, marker(START_NS + k * MS))
        buffer.trim()
        assert len(buffer) == min(k + 1, 10)
    assert len(buffer._stamps) <= 2 * COMPACT_AFTER
    assert kept(buffer) == list(range(4990, 5000))


def test_limits_are_checked():
    for limits in ({'window_ns': 0}, {'max_length': 0}):
        with pytest.raises(ValueError):
            PoseBuffer(**limits)


def rows(stamps_ms):
    positions = np.array([marker(START_NS + s * MS).position for s in stamps_ms]).reshape(-1, 3)
    quaternions = np.tile(quat.IDENTITY, (len(stamps_ms), 1))
    return [START_NS + s * MS for s in stamps_ms], positions, quaternions


def test_extend_takes_the_leading_increasing_part_up_to_stop_at():
    buffer = filled([0])
    assert buffer.extend(*rows([0, 1, 2])) == 0      # not newer than the newest
    assert buffer.extend(*rows([1, 2, 5, 5, 6])) == 3
    assert buffer.extend(*rows([6, 7, 8, 9]), stop_at_ns=START_NS + 7 * MS + 1) == 3
    assert buffer.extend(*rows([])) == 0
    assert kept(buffer) == [0, 1, 2, 5, 6, 7, 8]


@settings(max_examples=40, deadline=None, derandomize=True)
@given(runs=st.lists(st.lists(st.integers(-5, 60), max_size=12), max_size=8),
       window_ms=st.integers(1, 40), max_length=st.integers(1, 30), stop=st.integers(-5, 400))
def test_extend_is_append_one_by_one(runs, window_ms, max_length, stop):
    rng = np.random.default_rng(len(runs))
    by_rows = PoseBuffer(window_ms * MS, max_length)
    one_by_one = PoseBuffer(window_ms * MS, max_length)
    clock = 0
    for run in runs:
        stamps_ms = [clock + step for step in run]   # steps <= 0 break the run's order
        clock = max(stamps_ms, default=clock)
        stamps_ns, positions, _ = rows(stamps_ms)
        quaternions = quat.normalize(rng.standard_normal((len(run), 4)))
        stop_at_ns = START_NS + stop * MS
        count = by_rows.extend(stamps_ns, positions, quaternions, stop_at_ns)
        expected = 0
        for k, stamp in enumerate(stamps_ns):
            try:
                one_by_one.append(stamp, Pose(positions[k], quaternions[k]))
            except StampNotNewer:
                break
            expected += 1
            if stamp >= stop_at_ns:
                break
        assert count == expected
        by_rows.trim()
        one_by_one.trim()
    assert len(by_rows) == len(one_by_one) == len(by_rows.poses())
    for (stamp, pose), (other_stamp, other) in zip(by_rows.after(), one_by_one.after()):
        assert stamp == other_stamp
        assert np.array_equal(pose.position, other.position)
        assert np.array_equal(pose.quaternion, other.quaternion)
    for stamp_ms in range(-5, clock + 5, 3):
        pose, miss = by_rows.at(START_NS + stamp_ms * MS, 5 * MS, MS)
        other, other_miss = one_by_one.at(START_NS + stamp_ms * MS, 5 * MS, MS)
        assert miss == other_miss
        if pose is not None:
            assert np.array_equal(pose.position, other.position)
            assert np.array_equal(pose.quaternion, other.quaternion)
