"""The compact store of a whole recorded stream (the time-offset search reads both streams)."""

import tracemalloc

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.recorded_stream import RecordedStream

MS = 1_000_000


def random_poses(rng, n):
    return [Pose(rng.normal(size=3), quat.normalize(rng.normal(size=4))) for _ in range(n)]


def test_poses_come_back_as_they_were_given_with_their_covariances():
    rng = np.random.default_rng(1)
    poses = random_poses(rng, 5)
    covariance = np.diag(np.arange(1.0, 7.0))
    poses[2] = Pose(poses[2].position, poses[2].quaternion, covariance)
    stream = RecordedStream()
    for k, pose in enumerate(poses[:3]):
        stream.append(10 * k, pose)
    stream.extend([30, 40], np.array([p.position for p in poses[3:]]),
                  np.array([p.quaternion for p in poses[3:]]))
    assert len(stream) == 5
    assert stream.stamps().tolist() == [0, 10, 20, 30, 40]
    for (stamp, got), want, index in zip(stream, poses, range(5)):
        assert stamp == 10 * index
        np.testing.assert_array_equal(got.position, want.position)
        np.testing.assert_array_equal(got.quaternion, want.quaternion)
        np.testing.assert_array_equal(stream.pose(index).quaternion, want.quaternion)
        assert (got.covariance is None) == (index != 2)
    np.testing.assert_array_equal(stream.pose(2).covariance, covariance)
    np.testing.assert_array_equal(stream.positions()[3:], [p.position for p in poses[3:]])


def test_runs_are_cut_where_the_stamps_start_over_and_sorted_within():
    rng = np.random.default_rng(2)
    poses = random_poses(rng, 7)
    stamps = [100 * MS, 130 * MS, 120 * MS, 200 * MS, 5 * MS, 10 * MS, 10 * MS]
    covariance = np.eye(6)
    poses[5] = Pose(poses[5].position, poses[5].quaternion, covariance)
    stream = RecordedStream.of(zip(stamps, poses))
    first, second = stream.runs(time_jump_ns=50 * MS)   # 120 after 130: late, not a restart
    assert first.stamps().tolist() == [100 * MS, 120 * MS, 130 * MS, 200 * MS]
    np.testing.assert_array_equal(first.pose(1).quaternion, poses[2].quaternion)
    assert second.stamps().tolist() == [5 * MS, 10 * MS, 10 * MS]
    assert second.pose(1).covariance is covariance   # equal stamps keep their order
    assert second.pose(2).covariance is None
    assert len(stream.runs(time_jump_ns=10**12)) == 1


def test_a_lone_stale_or_future_stamp_is_left_out_not_a_restart():
    # One message stamped 10 s back (or ahead) cut a run of its stream alone: the time-offset
    # search then refused the recording ('the link stamps start over 1 time(s) and the sensor
    # stamps 0 time(s)'), where the replay had skipped it as a stale message.
    rng = np.random.default_rng(3)
    stamps = [k * 20 * MS for k in range(1000, 1012)]
    for index, odd in ((5, -10_000 * MS), (5, 10_000 * MS), (11, -10_000 * MS)):
        given = list(stamps)
        given[index] += odd
        (run,) = RecordedStream.of(zip(given, random_poses(rng, 12))).runs(50 * MS)
        assert run.stamps().tolist() == stamps[:index] + stamps[index + 1:]
    # Two together, a future first one, a future one before the last: left out alike.
    for odd in ({5: -10_000, 6: -10_000}, {0: 10_000}, {10: 10_000}):
        given = [stamp + odd.get(k, 0) * MS for k, stamp in enumerate(stamps)]
        (run,) = RecordedStream.of(zip(given, random_poses(rng, 12))).runs(50 * MS)
        assert run.stamps().tolist() == [s for k, s in enumerate(stamps) if k not in odd]
    # A restart lasts: two runs, as before; a slow stream (2 s apart) keeps every pose.
    restarted = stamps[:6] + [s - 10_000 * MS for s in stamps[6:]]
    assert len(RecordedStream.of(zip(restarted, random_poses(rng, 12))).runs(50 * MS)) == 2
    slow = [k * 2000 * MS for k in range(6)]
    (run,) = RecordedStream.of(zip(slow, random_poses(rng, 6))).runs(50 * MS)
    assert run.stamps().tolist() == slow


def test_a_pose_costs_its_stamp_and_seven_floats():
    """A list of (stamp, Pose) took about 0.9 KB a pose: 339 MB for 313k robot poses."""
    rng = np.random.default_rng(3)
    n = 20_000
    positions, quaternions = rng.normal(size=(n, 3)), rng.normal(size=(n, 4))
    one = Pose(positions[0], quaternions[0])
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        stream = RecordedStream()
        for k in range(n // 2):
            stream.append(k, one)
        stream.extend(list(range(n // 2, n)), positions[n // 2:], quaternions[n // 2:])
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert len(stream) == n
    # 64 bytes a pose, and the arrays' growth by up to about an eighth over what they hold
    assert held / n < 80


def test_a_run_is_looked_up_as_a_pose_buffer_would():
    rng = np.random.default_rng(4)
    poses = random_poses(rng, 4)
    run = RecordedStream.of(zip([10, 20, 20, 60], poses))
    assert run.at(9) is None and run.at(61) is None
    np.testing.assert_array_equal(run.at(10).position, poses[0].position)
    np.testing.assert_array_equal(run.at(20).position, poses[2].position)   # the last at 20
    quarter = run.at(15)   # up to the last pose at 20
    np.testing.assert_allclose(quarter.position, (poses[0].position + poses[2].position) / 2)
    halfway = run.at(40)   # across the 40 ns gap, from the last pose at 20
    np.testing.assert_allclose(halfway.position, (poses[2].position + poses[3].position) / 2)
    np.testing.assert_allclose(
        halfway.quaternion, quat.slerp(poses[2].quaternion, poses[3].quaternion, 0.5))
