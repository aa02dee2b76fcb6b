"""Tests of quatcal_ros.sim.simulation: known answers, noise statistics, outliers, streams."""

import subprocess
import sys

import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import SETUPS
from quatcal_ros.sim import simulation as sim

# Composing a handful of double-precision transforms loses a few ulps: 1e-12 is ~1000x that.
EXACT = 1e-12


def _object_pose(cell, link, sensor):
    """Return (what the data say, what it must be) for the constant object relation."""
    if cell.setup == 'eye_in_hand':
        return link @ cell.mounting @ sensor, cell.target        # L X S = T_base_obj
    return cell.mounting @ sensor, link @ cell.target             # M S = L T_link_obj


def _pose_error(a, b):
    """Return (position error in m, rotation error in rad) between two poses."""
    return (float(np.linalg.norm(a.position - b.position)),
            float(quat.angle_between(a.quaternion, b.quaternion)))


def _same_samples(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.stamp_ns == y.stamp_ns
        for pose_x, pose_y in ((x.link, y.link), (x.sensor, y.sensor)):
            assert_array_equal(pose_x.position, pose_y.position)
            assert_array_equal(pose_x.quaternion, pose_y.quaternion)


@pytest.mark.parametrize('setup', SETUPS)
def test_same_seed_same_data_other_seed_other_data(setup):
    def run(seed):
        rng = np.random.default_rng(seed)
        cell = sim.random_cell(rng, setup)
        return cell, sim.samples(rng, cell, 20, 0.3, 0.002, outlier_fraction=0.2)

    cell_a, (samples_a, outliers_a) = run(5)
    cell_b, (samples_b, outliers_b) = run(5)
    assert_array_equal(cell_a.mounting.quaternion, cell_b.mounting.quaternion)
    _same_samples(samples_a, samples_b)
    assert outliers_a == outliers_b
    _, (samples_c, _) = run(6)
    assert not np.allclose(samples_a[0].link.position, samples_c[0].link.position)


@pytest.mark.parametrize('setup', SETUPS)
@pytest.mark.parametrize('seed', range(5))
def test_noise_free_samples_satisfy_the_hand_eye_relation_exactly(setup, seed):
    rng = np.random.default_rng(seed)
    cell = sim.random_cell(rng, setup)
    samples, outliers = sim.samples(rng, cell, 30)
    assert outliers == []
    for sample in samples:
        position_error, angle_error = _pose_error(*_object_pose(cell, sample.link, sample.sensor))
        assert position_error < EXACT and angle_error < 1e-7   # arccos near 1: ~sqrt(eps)
        measured, expected = _object_pose(cell, sample.link, sample.sensor)
        assert_allclose(measured.as_matrix(), expected.as_matrix(), rtol=0, atol=EXACT)


def test_stamps_are_integers_on_the_period():
    rng = np.random.default_rng(1)
    samples, _ = sim.samples(rng, sim.random_cell(rng), 4, start_ns=10 ** 18, period_ns=7)
    assert [s.stamp_ns for s in samples] == [10 ** 18 + 7 * i for i in range(4)]
    assert all(type(s.stamp_ns) is int for s in samples)


@pytest.mark.parametrize('setup', SETUPS)
@pytest.mark.parametrize('seed', range(10))
def test_random_cell_is_plausible(setup, seed):
    cell = sim.random_cell(np.random.default_rng(seed), setup)
    assert cell.setup == setup
    assert_allclose(np.linalg.norm(cell.mounting.quaternion), 1.0, atol=1e-12)
    at_home = cell.sensor_pose(cell.home)
    distance = np.linalg.norm(at_home.position)
    assert 0.5 <= distance <= 1.01                        # 0.5-1 m, lateral offset <= 5 cm
    assert at_home.position[2] > 0.98 * distance           # in front of the sensor (z axis)
    normal = at_home.rotation[:, 2]                        # the marker faces the sensor
    assert -normal @ at_home.position / distance > np.cos(np.radians(21.0))
    offset = cell.mounting if setup == 'eye_in_hand' else cell.target
    assert 0.05 <= np.linalg.norm(offset.position) <= 0.15


@pytest.mark.parametrize('setup', SETUPS)
def test_random_cell_keeps_a_given_mounting(setup):
    mounting = Pose.create([0.3, -0.2, 0.9], sim.quaternion_wxyz_from_rpy(0.1, 2.5, -1.0))
    cell = sim.random_cell(np.random.default_rng(3), setup, mounting=mounting)
    assert cell.mounting is mounting
    at_home = cell.sensor_pose(cell.home)
    assert 0.5 <= np.linalg.norm(at_home.position) <= 1.01
    sim.stop_poses(np.random.default_rng(4), cell, 10)   # the object stays reachable in view


def test_cell_rejects_an_unknown_setup():
    with pytest.raises(ValueError, match='setup'):
        sim.random_cell(np.random.default_rng(0), 'eye_on_table')


@pytest.mark.parametrize('setup', SETUPS)
def test_stop_poses_turn_about_the_pivot_and_excite_all_axes(setup):
    rng = np.random.default_rng(11)
    cell = sim.random_cell(rng, setup)
    poses = sim.stop_poses(rng, cell, 40, rotation_spread_deg=30.0)
    pivot_link = cell.mounting.position if setup == 'eye_in_hand' else cell.target.position
    home_pivot = cell.home.position + cell.home.rotation @ pivot_link
    rotation_vectors = []
    for link in poses:
        turn = quat.multiply(link.quaternion, quat.conjugate(cell.home.quaternion))
        assert quat.rotation_angle(turn) <= np.radians(30.0) + 1e-9
        rotation_vectors.append(quat.rotation_vector(turn))
        # The pivot (sensor or object origin) only moves by the 10-20 cm shift.
        shift = link.position + link.rotation @ pivot_link - home_pivot
        assert 0.10 - 1e-12 <= np.linalg.norm(shift) <= 0.20 + 1e-12
        seen = cell.sensor_pose(link)
        assert np.degrees(np.arccos(seen.position[2] / np.linalg.norm(seen.position))) <= 45.0
    # Rotations about every axis: the smallest singular value is not far below the largest.
    singular = np.linalg.svd(np.array(rotation_vectors), compute_uv=False)
    assert singular[-1] > 0.4 * singular[0]


def test_stop_poses_say_when_the_object_cannot_stay_in_view():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match='rotation_spread_deg'):
        sim.stop_poses(rng, sim.random_cell(rng), 3, max_view_angle_deg=0.01, max_tries=20)


def test_noise_statistics_match_the_configuration():
    n, sigma_deg, sigma_m = 4000, 0.5, 0.002
    cell = sim.random_cell(np.random.default_rng(2))
    clean, _ = sim.samples(np.random.default_rng(9), cell, n)
    noisy, _ = sim.samples(np.random.default_rng(9), cell, n, sigma_deg, sigma_m)
    rotation = np.array([quat.rotation_vector(quat.multiply(b.sensor.quaternion,
                                                            quat.conjugate(a.sensor.quaternion)))
                         for a, b in zip(clean, noisy)])
    translation = np.array([b.sensor.position - a.sensor.position for a, b in zip(clean, noisy)])
    # Same stops with and without noise (the noise is drawn after them).
    assert_array_equal(clean[7].link.position, noisy[7].link.position)
    # Per-axis std: the relative standard error of a std estimate is 1/sqrt(2 n) = 1.1 %;
    # 5 % is more than 4 standard errors.  Means: 4 standard errors of the mean.
    assert_allclose(np.degrees(rotation.std(axis=0)), sigma_deg, rtol=0.05)
    assert_allclose(translation.std(axis=0), sigma_m, rtol=0.05)
    assert np.all(np.abs(np.degrees(rotation.mean(axis=0))) < 4 * sigma_deg / np.sqrt(n))
    assert np.all(np.abs(translation.mean(axis=0)) < 4 * sigma_m / np.sqrt(n))
    # Isotropic Gaussian rotation vector: the angle's RMS is sqrt(3) sigma (chi, 3 dof).
    rms_angle = np.degrees(np.sqrt(np.mean(np.sum(rotation ** 2, axis=1))))
    assert_allclose(rms_angle, np.sqrt(3.0) * sigma_deg, rtol=0.05)
    # The link poses are exact unless link noise is asked for.
    assert all(np.array_equal(a.link.quaternion, b.link.quaternion)
               for a, b in zip(clean, noisy))


def test_link_noise_is_applied_to_the_link_poses():
    cell = sim.random_cell(np.random.default_rng(2))
    clean, _ = sim.samples(np.random.default_rng(9), cell, 2000)
    noisy, _ = sim.samples(np.random.default_rng(9), cell, 2000, link_rotation_noise_deg=0.1,
                           link_translation_noise_m=0.0005)
    angles = [quat.angle_between(a.link.quaternion, b.link.quaternion)
              for a, b in zip(clean, noisy)]
    offsets = np.array([b.link.position - a.link.position for a, b in zip(clean, noisy)])
    # RMS angle sqrt(3) sigma; 2000 samples: relative standard error < 1 %, 5 % allowed.
    assert_allclose(np.degrees(np.sqrt(np.mean(np.square(angles)))), np.sqrt(3) * 0.1,
                    rtol=0.05)
    assert_allclose(offsets.std(axis=0), 0.0005, rtol=0.08)   # 1.6 % standard error
    assert_array_equal(clean[3].sensor.quaternion, noisy[3].sensor.quaternion)


@pytest.mark.parametrize('setup', SETUPS)
def test_outliers_are_flagged_and_only_they_break_the_relation(setup):
    rng = np.random.default_rng(21)
    cell = sim.random_cell(rng, setup)
    samples, outliers = sim.samples(rng, cell, 50, outlier_fraction=0.2)
    assert len(outliers) == 10 and outliers == sorted(set(outliers))
    broken = [i for i, s in enumerate(samples)
              if _pose_error(*_object_pose(cell, s.link, s.sensor))[1] > 1e-6]
    assert broken == outliers
    for i in outliers:   # a bad detection turns the object by 30 deg or more
        assert _pose_error(*_object_pose(cell, samples[i].link, samples[i].sensor))[1] > \
            np.radians(29.9)


def test_outlier_kinds_flip_about_the_objects_own_axes():
    q = sim.random_quaternions(np.random.default_rng(0), 1)
    R = quat.matrix_from_quaternion(q[0])
    uniforms = np.array([[0.1, 0.5, 0.5, 0.5], [0.5, 0.5, 0.5, 0.5], [0.9, 0.25, 0.25, 1.0]])
    out, kinds = sim.corrupt_orientations(np.repeat(q, 3, axis=0), uniforms)
    assert kinds == ['flip_x', 'flip_y', 'random']
    flip_x, flip_y = quat.matrix_from_quaternion(out[0]), quat.matrix_from_quaternion(out[1])
    assert_allclose(flip_x[:, 0], R[:, 0], atol=EXACT)        # own x kept, z reversed
    assert_allclose(flip_x[:, 2], -R[:, 2], atol=EXACT)
    assert_allclose(flip_y[:, 1], R[:, 1], atol=EXACT)
    assert_allclose(flip_y[:, 2], -R[:, 2], atol=EXACT)
    assert_allclose(quat.angle_between(out[2], q[0]), np.pi, atol=1e-7)   # u3 = 1: 180 deg


def test_rpy_follows_the_ros_convention():
    roll, pitch, yaw = 0.3, -0.7, 2.1

    def rot(axis, angle):
        return quat.matrix_from_quaternion(quat.from_axis_angle(np.eye(3)[axis], angle))

    expected = rot(2, yaw) @ rot(1, pitch) @ rot(0, roll)
    assert_allclose(quat.matrix_from_quaternion(sim.quaternion_wxyz_from_rpy(roll, pitch, yaw)),
                    expected, atol=EXACT)


def test_minimum_jerk_starts_and_ends_at_rest():
    s = sim.minimum_jerk(np.array([-1.0, 0.0, 1e-4, 0.5, 1.0 - 1e-4, 1.0, 2.0]))
    assert_allclose(s, [0.0, 0.0, 0.0, 0.5, 1.0, 1.0, 1.0], atol=1e-10)


def test_grid_indices_invert_grid_times():
    for rate in (30.0, 500.0, 1000.0, 7.3):
        times = sim.grid_times_ns(np.arange(200), rate)
        for i, t in enumerate(times.tolist()):
            assert sim.last_grid_index(t, rate) == i
            assert sim.last_grid_index(t - 1, rate) == i - 1
    assert sim.last_grid_index(-5, 30.0) == -1


def test_stop_and_go_holds_still_then_moves_smoothly():
    rng = np.random.default_rng(8)
    cell = sim.random_cell(rng)
    robot = sim.StopAndGo(rng, cell, still_s=1.0, move_s=2.0, n_stops=3)
    assert robot.duration_ns == 3 * 3 * 10 ** 9 - 2 * 10 ** 9
    t = np.arange(0, 10 * 10 ** 9, 10 ** 6)   # 1 kHz for 10 s, past the end
    positions, quaternions = robot.link_poses(t)
    still = robot.is_still(t)
    for k in range(3):
        first, last = robot.still_interval_ns(k)
        inside = (t >= first) & (t < last) if k < 2 else t >= first
        assert still[inside].all()
        assert np.all(positions[inside] == robot.stop(k).position)
    assert not still[(t > 1.1e9) & (t < 2.9e9)].any()
    # Smooth: the speed peaks at 1.875 d / T mid-move (minimum jerk); 1 ms steps at 1 kHz.
    stops = [robot.stop(k) for k in range(3)]
    distance = max(np.linalg.norm(b.position - a.position) for a, b in zip(stops, stops[1:]))
    turn = max(quat.angle_between(a.quaternion, b.quaternion) for a, b in zip(stops, stops[1:]))
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert_allclose(steps.max(), 1.875 * distance / 2.0 * 1e-3, rtol=0.01)
    angles = quat.angle_between(quaternions[1:], quaternions[:-1])
    assert_allclose(angles.max(), 1.875 * turn / 2.0 * 1e-3, rtol=0.01)


def test_stop_and_go_is_the_same_in_chunks_and_forever():
    cell = sim.random_cell(np.random.default_rng(1))
    t = np.arange(0, 12 * 10 ** 9, 3_000_000)
    whole = sim.StopAndGo(np.random.default_rng(3), cell, n_stops=5).link_poses(t)
    forever = sim.StopAndGo(np.random.default_rng(3), cell, n_stops=0)
    parts = [forever.link_poses(chunk) for chunk in np.array_split(t, 37)]
    assert_allclose(np.concatenate([p for p, _ in parts]), whole[0], rtol=0, atol=EXACT)
    assert_allclose(np.concatenate([q for _, q in parts]), whole[1], rtol=0, atol=EXACT)


def test_sensor_model_is_the_same_in_batches():
    rng = np.random.default_rng(0)
    truth_p = rng.normal(size=(100, 3))
    truth_q = sim.random_quaternions(rng, 100)

    def model():
        return sim.SensorModel(np.random.default_rng(5), 0.3, 0.01, 0.2, 0.1)

    whole = model().observe(truth_p, truth_q)
    batched_model = model()
    parts = [batched_model.observe(truth_p[s], truth_q[s])
             for s in (slice(0, 1), slice(1, 40), slice(40, 41), slice(41, 100))]
    for i, whole_part in enumerate(whole):
        assert_array_equal(np.concatenate([part[i] for part in parts]), whole_part)


@pytest.mark.parametrize('setup', SETUPS)
def test_streams_timing_drops_and_exact_relation(setup):
    rng = np.random.default_rng(13)
    cell = sim.random_cell(rng, setup)
    streams = sim.stop_and_go_streams(
        rng, cell, n_stops=40, link_rate_hz=500.0, sensor_rate_hz=50.0, latency_s=0.03,
        drop_probability=0.1, start_ns=sim.DEFAULT_START_NS)
    start, end = sim.DEFAULT_START_NS, sim.DEFAULT_START_NS + (40 * 3.5 - 2.0) * 1e9
    link_stamps = np.array([s for s, _ in streams.link])
    assert link_stamps[0] == start and np.all(np.diff(link_stamps) == 2_000_000)
    assert abs(link_stamps[-1] - end) < 2e6
    sensor_stamps = np.array([s for s, _ in streams.sensor])
    assert np.all((sensor_stamps - start) % 20_000_000 == 0)
    assert_array_equal(np.array(streams.sensor_delivery_ns) - sensor_stamps, 30_000_000)
    frames = int((end - start) // 20_000_000) + 1
    dropped = 1.0 - len(streams.sensor) / frames
    # 6901 frames, p = 0.1: binomial standard error 0.0036; 0.015 is four of them.
    assert abs(dropped - 0.1) < 0.015
    assert streams.truth is cell.mounting and len(streams.stops) == len(streams.stills) == 40
    # The sensor stamps fall on link stamps (50 Hz vs 500 Hz): the relation holds exactly.
    links = dict(streams.link)
    for stamp, seen in streams.sensor:
        position_error, _ = _pose_error(*_object_pose(cell, links[stamp], seen))
        assert position_error < EXACT
    # During each still interval the link pose is the stop pose.
    link_positions = np.array([pose.position for _, pose in streams.link])
    for stop, (first, last) in zip(streams.stops, streams.stills):
        held = link_positions[(link_stamps >= first) & (link_stamps < last)]
        assert len(held) == 750 and np.all(held == stop.position)


def test_streams_with_noise_and_outliers():
    rng = np.random.default_rng(14)
    cell = sim.random_cell(rng)
    streams = sim.stop_and_go_streams(
        rng, cell, n_stops=10, link_rate_hz=500.0, sensor_rate_hz=50.0, drop_probability=0.0,
        rotation_noise_deg=0.2, translation_noise_m=0.001, outlier_fraction=0.05)
    links = dict(streams.link)
    errors = np.array([_pose_error(*_object_pose(cell, links[stamp], seen))[1]
                       for stamp, seen in streams.sensor])
    flagged = np.zeros(len(errors), dtype=bool)
    flagged[streams.sensor_outliers] = True
    # Noise of 0.2 deg per axis gives angles far below 5 deg; flips are 30 deg or more.
    assert_array_equal(errors > np.radians(5.0), flagged)
    assert 0.02 < flagged.mean() < 0.08   # 1701 frames at p = 0.05: 5 standard errors


def test_streams_for_ten_minutes_at_one_kilohertz():
    rng = np.random.default_rng(0)
    streams = sim.stop_and_go_streams(rng, sim.random_cell(rng), n_stops=172,
                                      link_rate_hz=1000.0, sensor_rate_hz=30.0)
    assert len(streams.link) == 600_001
    assert streams.link[-1][0] - streams.link[0][0] == 600 * 10 ** 9


def test_core_module_imports_no_ros(repo_root):
    code = ('import sys, quatcal_ros.sim.simulation; '
            'bad = [m for m in sys.modules if m.split(".")[0] in '
            '("rclpy", "geometry_msgs", "std_msgs", "builtin_interfaces")]; '
            'sys.exit(str(bad) if bad else 0)')
    subprocess.run([sys.executable, '-c', code], check=True, cwd=repo_root)


def test_delivery_order_is_the_publishing_order():
    rng = np.random.default_rng(4)
    streams = sim.stop_and_go_streams(rng, sim.random_cell(rng), 2, latency_s=0.03)
    events = streams.delivery_order()
    assert len(events) == len(streams.link) + len(streams.sensor)
    dues = [due for due, _, _, _ in events]
    assert dues == sorted(dues)
    assert [e[2] for e in events if e[1] == 'sensor'] == [s for s, _ in streams.sensor]
    assert all(due == stamp for due, name, stamp, _ in events if name == 'link')
    assert {e[1] for e in streams.delivery_order(('a', 'b'))} == {'a', 'b'}
