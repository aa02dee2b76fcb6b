"""Tests of stream.capture: still detection, averaging, manual refusals, continuous mode."""

import numpy as np
from numpy.testing import assert_allclose
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.sim import simulation as sim
from quatcal_ros.stream.capture import Capture, CaptureConfig, pose_change
from quatcal_ros.stream.pairing import Pair

START_NS = sim.DEFAULT_START_NS
MS = 1_000_000


def stop_and_go_pairs(rng, n_stops, rate_hz=30.0, noise_deg=0.3, noise_m=0.001, drop=0.1):
    """
    Make pairs at rate_hz of a robot visiting n_stops stops; a tenth of the frames dropped.

    Returns (cell, trajectory, pairs); the sensor poses have Gaussian noise (per axis).
    """
    cell = sim.random_cell(rng)
    trajectory = sim.StopAndGo(rng, cell, still_s=1.5, move_s=2.0, n_stops=n_stops)
    last = sim.last_grid_index(trajectory.duration_ns, rate_hz)
    t = sim.grid_times_ns(np.arange(last + 1), rate_hz)
    link_p, link_q = trajectory.link_poses(t)
    sensor_p, sensor_q = sim.add_pose_noise(rng, *cell.sensor_poses(link_p, link_q),
                                            noise_deg, noise_m)
    kept = rng.random(len(t)) >= drop
    pairs = [Pair(START_NS + int(t[i]), Pose(link_p[i], link_q[i]),
                  Pose(sensor_p[i], sensor_q[i])) for i in np.flatnonzero(kept)]
    return cell, trajectory, pairs


def still_pairs(rng, link, sensor, start_ns, duration_s, rate_hz, noise_deg=0.0, noise_m=0.0):
    """Pairs of a still robot: fixed link pose, sensor pose with noise."""
    count = int(duration_s * rate_hz)
    p, q = sim.add_pose_noise(rng, np.tile(sensor.position, (count, 1)),
                              np.tile(sensor.quaternion, (count, 1)), noise_deg, noise_m)
    return [Pair(start_ns + int(round(i * 1e9 / rate_hz)), link, Pose(p[i], q[i]))
            for i in range(count)]


def run(capture, pairs):
    """Feed pairs; return the samples taken."""
    return [s for s in (capture.add_pair(pair) for pair in pairs) if s is not None]


def turned(pose, degrees, axis=(0.0, 0.0, 1.0), shift=(0.0, 0.0, 0.0)):
    """Return the pose turned about `axis` (its own frame) and shifted (parent frame)."""
    turn = quat.from_axis_angle(axis, np.radians(degrees))
    return Pose(pose.position + np.asarray(shift), quat.multiply(pose.quaternion, turn))


def rotation_error_deg(pose, truth):
    return float(np.degrees(quat.angle_between(pose.quaternion, truth.quaternion)))


def test_auto_takes_one_averaged_sample_per_stop():
    rng = np.random.default_rng(10)
    n_stops = 6
    cell, trajectory, pairs = stop_and_go_pairs(rng, n_stops)
    config = CaptureConfig()
    samples = run(Capture(config), pairs)
    assert len(samples) == n_stops
    single_frame_errors, averaged_errors = [], []
    for k, sample in enumerate(samples):
        stop = trajectory.stop(k)
        angle, distance = pose_change(sample.link, stop)
        # Every pair averaged is within the bands of the newest one, which is at the stop.
        assert angle <= config.rotation_band_deg and distance <= config.translation_band_m
        averaged_errors.append(rotation_error_deg(sample.sensor, cell.sensor_pose(sample.link)))
        first, last = trajectory.still_interval_ns(k)
        single_frame_errors += [rotation_error_deg(p.sensor, cell.sensor_pose(p.link))
                                for p in pairs if START_NS + first <= p.stamp_ns < START_NS + last]
    # About 13 frames per average: the error should shrink ~3.6 times; ask for 2.
    assert np.mean(averaged_errors) < 0.5 * np.mean(single_frame_errors)


def test_auto_at_a_fast_pair_rate_averages_exactly_the_still_window():
    rng = np.random.default_rng(11)
    link = Pose.create([0.4, 0.1, 0.5], quat.normalize(rng.standard_normal(4)))
    sensor = Pose.create([0.0, 0.1, 0.7], quat.normalize(rng.standard_normal(4)))
    pairs = still_pairs(rng, link, sensor, START_NS, 2.0, 1000.0, noise_deg=0.1, noise_m=0.0005)
    samples = run(Capture(CaptureConfig(window_ns=500 * MS)), pairs)
    assert len(samples) == 1
    window = pairs[:501]   # the first moment 0.5 s of stamps are covered: 501 pairs at 1 kHz
    assert samples[0].stamp_ns == START_NS + 250 * MS
    expected_q = quat.average([p.sensor.quaternion for p in window])
    expected_p = np.mean([p.sensor.position for p in window], axis=0)
    # Same formula on the same numbers: only summation order differs.
    assert_allclose(samples[0].sensor.quaternion, expected_q, rtol=0.0, atol=1e-12)
    assert_allclose(samples[0].sensor.position, expected_p, rtol=0.0, atol=1e-12)
    assert_allclose(samples[0].link.position, link.position, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize('seed', range(4))
def test_the_quick_stillness_check_agrees_with_the_reasons(seed):
    """_is_still (one pair decides while moving) is _still_reason() is None at every pair."""
    rng = np.random.default_rng(seed)
    # Sensor noise near its bands, link bands from strict to loose: windows on both sides.
    _, _, pairs = stop_and_go_pairs(rng, 4, noise_deg=0.2, noise_m=0.001)
    band_deg, band_m = [(0.2, 0.001), (5.0, 0.05), (30.0, 0.3), (60.0, 0.5)][seed]
    capture = Capture(CaptureConfig(rotation_band_deg=band_deg, translation_band_m=band_m,
                                    min_departure_deg=2 * band_deg, min_departure_m=2 * band_m,
                                    sensor_rotation_band_deg=0.8,
                                    sensor_translation_band_m=0.003))
    verdicts = []
    for pair in pairs:
        capture.add_pair(pair)
        verdicts.append(capture._is_still())
        assert verdicts[-1] == (capture._still_reason() is None)
    assert any(verdicts) and not all(verdicts)


def test_auto_needs_a_real_motion_before_the_next_sample():
    rng = np.random.default_rng(12)
    link = Pose.create([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0])
    sensor = Pose.create([0.0, 0.0, 0.7], [0.0, 1.0, 0.0, 0.0])
    capture = Capture(CaptureConfig(min_departure_deg=2.0, min_departure_m=0.02))
    t = START_NS

    def stand(pose, seconds):
        nonlocal t
        pairs = still_pairs(rng, pose, sensor, t, seconds, 30.0, noise_deg=0.2)
        t = pairs[-1].stamp_ns + 33 * MS
        return run(capture, pairs)

    assert len(stand(link, 10.0)) == 1                            # one sample per stop
    assert stand(turned(link, 1.5), 3.0) == []                    # 1.5 deg: not a motion
    assert stand(link, 3.0) == []
    assert len(stand(turned(link, 3.0), 3.0)) == 1                # 3 deg: a motion
    assert len(stand(turned(link, 3.0, shift=(0.03, 0, 0)), 3.0)) == 1   # 3 cm alone is too
    assert stand(turned(link, 3.0, shift=(0.03, 0, 0)), 3.0) == []


def flipped(pairs, rng, share, degrees=30.0):
    """Return `pairs` with `share` of their sensor poses turned by `degrees` (a marker flip)."""
    flips = rng.random(len(pairs)) < share
    return [Pair(p.stamp_ns, p.link, turned(p.sensor, degrees, axis=(1.0, 0.0, 0.0)))
            if flip else p for p, flip in zip(pairs, flips)], int(flips.sum())


def test_a_marker_that_flips_for_a_frame_costs_the_frame_not_the_stop():
    # A tenth of the frames flipped: a still window with one of them was not still, and 12 of
    # 15 stops of a recording gave no sample, without a word.
    rng = np.random.default_rng(15)
    cell, trajectory, pairs = stop_and_go_pairs(rng, 8, noise_deg=0.2)
    pairs, flips = flipped(pairs, rng, 0.1)
    capture = Capture(CaptureConfig())
    samples = run(capture, pairs)
    assert len(samples) == 8
    for sample in samples:   # no flip averaged in: one of ~13 frames would be 2 deg off
        assert rotation_error_deg(sample.sensor, cell.sensor_pose(sample.link)) < 0.3
    assert 0 < capture.sensor_jumps <= flips


def test_frames_left_out_are_exactly_the_jumps_and_a_moved_object_still_waits():
    rng = np.random.default_rng(16)
    link = Pose.create([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0])
    sensor = Pose.create([0.0, 0.0, 0.7], [0.0, 1.0, 0.0, 0.0])
    pairs = still_pairs(rng, link, sensor, START_NS, 0.6, 50.0, noise_deg=0.1, noise_m=0.0002)
    jumped = {5, 6, 12}   # inside the window, a run of two among them
    pairs = [Pair(p.stamp_ns, p.link, turned(p.sensor, 20.0)) if i in jumped else p
             for i, p in enumerate(pairs)]
    capture = Capture(CaptureConfig())
    (sample,) = run(capture, pairs)
    window = [p for i, p in enumerate(pairs[:26]) if i not in jumped]   # 0.5 s at 50 Hz
    assert_allclose(sample.sensor.quaternion,
                    quat.average([p.sensor.quaternion for p in window]), atol=1e-12)
    assert_allclose(sample.sensor.position,
                    np.mean([p.sensor.position for p in window], axis=0), atol=1e-12)
    assert capture.sensor_jumps == 3
    # The object moved (knocked) a fifth of a window ago: the poses before are out of band,
    # the oldest among them: not still until a whole window at the new place.
    moved = turned(sensor, 0.0, shift=(0.02, 0.0, 0.0))
    capture = Capture(CaptureConfig(mode='manual'))
    before = still_pairs(rng, link, sensor, START_NS, 0.1, 50.0)
    after = still_pairs(rng, link, moved, START_NS + 100 * MS, 0.5, 50.0)
    run(capture, before + after)
    refused, reason = capture.capture_now(after[-1].stamp_ns)
    assert refused is None and reason.startswith('sensor pose is not steady: 0 deg, 20 mm')
    later = still_pairs(rng, link, moved, START_NS + 600 * MS, 0.2, 50.0)
    run(capture, later)
    sample, text = capture.capture_now(later[-1].stamp_ns)
    assert sample is not None and 'left out' not in text
    assert_allclose(sample.sensor.position, moved.position, atol=1e-12)


def test_a_frame_just_outside_the_sensor_bands_is_noise_and_averaged():
    # Two frames 1.5 deg off (the band 1 deg, a jump from 2): the window is still and they
    # are averaged in. Every frame had to be within the band of the newest: a manual capture
    # at a real stop with 0.3 deg of detector noise per axis was refused 7 times in 10.
    link = Pose.create([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0])
    sensor = Pose.create([0.0, 0.0, 0.7], [0.0, 1.0, 0.0, 0.0])
    pairs = [Pair(START_NS + i * 20 * MS, link, turned(sensor, 1.5 if i in (30, 41) else 0.0))
             for i in range(51)]
    capture = Capture(CaptureConfig(mode='manual'))
    run(capture, pairs)
    sample, text = capture.capture_now(pairs[-1].stamp_ns)
    assert text == 'averaged 26 pairs over 0.5 s'
    window = [p.sensor.quaternion for p in pairs[25:]]
    assert_allclose(sample.sensor.quaternion, quat.average(window), atol=1e-12)
    assert capture.sensor_jumps == 0
    # One in three frames outside the band is too noisy a detector: refused (auto mode too),
    # and counted as an unsteady sensor for the advice to widen its bands.
    noisy = [Pair(p.stamp_ns, link, turned(sensor, 1.5 if i % 3 == 1 else 0.0))
             for i, p in enumerate(pairs)]
    auto = Capture(CaptureConfig())
    assert run(auto, noisy) == [] and auto.unsteady_sensor > 0
    # The oldest frame outside the band is a motion, not noise: refused.
    pairs[25] = Pair(pairs[25].stamp_ns, link, turned(sensor, 1.5))
    capture = Capture(CaptureConfig(mode='manual'))
    run(capture, pairs)
    assert capture.capture_now(pairs[-1].stamp_ns)[1].startswith('sensor pose is not steady')


def test_manual_captures_at_stops_with_ordinary_detector_noise_mostly_succeed():
    # 0.3 deg per axis and 1 mm of detector noise, the default bands, a 1 s stop at 30 Hz:
    # 30 of 100 accepted before (every frame within the band of the newest), 77 now.
    link = Pose.create([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0])
    sensor = Pose.create([0.0, 0.0, 0.7], [0.0, 1.0, 0.0, 0.0])
    accepted = 0
    for seed in range(100):
        capture = Capture(CaptureConfig(mode='manual'))
        pairs = still_pairs(np.random.default_rng(seed), link, sensor, START_NS, 1.0, 30.0,
                            noise_deg=0.3, noise_m=0.001)
        run(capture, pairs)
        accepted += capture.capture_now(pairs[-1].stamp_ns)[0] is not None
    assert accepted >= 60, accepted


def test_manual_mode_captures_only_on_request():
    rng = np.random.default_rng(13)
    link = Pose.create([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0])
    sensor = Pose.create([0.0, 0.0, 0.7], [0.0, 1.0, 0.0, 0.0])
    capture = Capture(CaptureConfig(mode='manual'))
    pairs = still_pairs(rng, link, sensor, START_NS, 2.0, 30.0, noise_deg=0.2)
    assert run(capture, pairs) == []
    now = pairs[-1].stamp_ns + 50 * MS
    sample, text = capture.capture_now(now)
    assert sample is not None and text.startswith('averaged ')
    assert_allclose(sample.link.position, link.position, rtol=0.0, atol=1e-12)
    sample, reason = capture.capture_now(now)
    assert sample is None
    assert reason.startswith('no motion since the last sample (link 0 deg, 0 mm away; need 2 '
                             'deg or 20 mm): move the robot')


def test_manual_refusals_say_why():
    rng = np.random.default_rng(14)
    link = Pose.create([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0])
    sensor = Pose.create([0.0, 0.0, 0.7], [0.0, 1.0, 0.0, 0.0])
    config = CaptureConfig(mode='manual', window_ns=500 * MS, rotation_band_deg=0.2)
    capture = Capture(config)
    no_pairs = ('no paired poses in the last 1.0 s: check that both topics publish and that '
                'their stamps use the same clock')
    assert capture.capture_now(START_NS) == (None, no_pairs)

    # Rotating at 6.4 deg/s: 3.2 deg in the last 0.5 s.
    moving = [Pair(START_NS + i * 20 * MS, turned(link, 0.128 * i), sensor) for i in range(51)]
    run(capture, moving)
    now = moving[-1].stamp_ns
    assert capture.capture_now(now) == (
        None, 'robot is moving: link rotated 3.2 deg in the last 0.5 s (band 0.2 deg)')
    assert capture.capture_now(now + 1001 * MS) == (None, no_pairs)

    capture = Capture(config)
    sliding = [Pair(START_NS + i * 20 * MS, turned(link, 0.0, shift=(0.0002 * i, 0, 0)), sensor)
               for i in range(51)]
    run(capture, sliding)
    assert capture.capture_now(now)[1] == (
        'robot is moving: link moved 5 mm in the last 0.5 s (band 1 mm)')

    capture = Capture(config)
    wobbling = [Pair(START_NS + i * 20 * MS, link, turned(sensor, 3.0 * (i % 2)))
                for i in range(51)]
    run(capture, wobbling)
    assert capture.capture_now(now)[1].startswith(
        'sensor pose is not steady: 3 deg, 0 mm in the last 0.5 s (bands 1 deg, 5 mm; the '
        'rotation beyond): is the object fixed and detected reliably? Just after a stop the '
        'sensor (its latency) may still show the motion: try again in a moment.')

    capture = Capture(config)   # one in five frames jumps: a sample, saying so
    flipping = [Pair(START_NS + i * 20 * MS, link, turned(sensor, 3.0 * (i % 5 == 2)))
                for i in range(51)]
    run(capture, flipping)
    sample, text = capture.capture_now(now)
    assert text == ('averaged 26 link and 21 sensor poses over 0.5 s, 5 sensor pose(s) left '
                    'out: they jumped over 2x the sensor bands (a marker flip?)')
    assert_allclose(sample.sensor.quaternion, sensor.quaternion, atol=1e-12)

    capture = Capture(config)
    run(capture, still_pairs(rng, link, sensor, START_NS, 0.3, 30.0))
    assert capture.capture_now(START_NS + 300 * MS)[1] == (
        'paired poses cover only 0.27 s of the 0.5 s still window: wait and try again')

    capture = Capture(config)
    sparse = [Pair(START_NS + i * 600 * MS, link, sensor) for i in range(2)]
    run(capture, sparse)
    assert capture.capture_now(sparse[-1].stamp_ns)[1] == (
        'only 2 paired poses in the last 0.6 s (need 3): is the sensor dropping frames?')


def test_a_manual_capture_in_continuous_mode_counts_the_motion_since_the_last_sample():
    # Continuous mode never noted the departure: every ~/capture was refused as 'no motion
    # since the last sample (link 19.79 deg, 289.06 mm away; need 2 deg or 20 mm)'.
    rng = np.random.default_rng(16)
    link = Pose.create([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0])
    sensor = Pose.create([0.0, 0.0, 0.7], [0.0, 1.0, 0.0, 0.0])
    capture = Capture(CaptureConfig(mode='continuous'))
    first = still_pairs(rng, link, sensor, START_NS, 1.0, 30.0)
    assert len(run(capture, first)) == 1                    # the first pair starts the series
    later = still_pairs(rng, turned(link, 3.0), sensor, first[-1].stamp_ns + 2000 * MS, 1.0,
                        30.0)
    run(capture, later)
    sample, text = capture.capture_now(later[-1].stamp_ns)
    assert sample is not None, text


def test_continuous_mode_takes_pairs_spaced_by_rotation():
    rng = np.random.default_rng(15)
    start = Pose.create([0.4, 0.0, 0.5], quat.normalize(rng.standard_normal(4)))
    axis = quat.normalize(rng.standard_normal(3))
    # 30 deg/s at 30 Hz: 1 deg between pairs, 120 deg in all.
    pairs = [Pair(START_NS + i * 33 * MS, turned(start, 1.0 * i, axis), start)
             for i in range(121)]
    capture = Capture(CaptureConfig(mode='continuous', continuous_step_deg=4.5))
    samples = run(capture, pairs)
    assert samples[0].link is pairs[0].link                 # the first pair starts the series
    steps = [pose_change(b.link, a.link)[0] for a, b in zip(samples, samples[1:])]
    # 4.5 deg is first reached 5 pairs (5 deg) on; 1e-6 deg covers the rounding of the angle.
    assert_allclose(steps, 5.0, rtol=0.0, atol=1e-6)
    assert len(samples) == 25
    by_stamp = {pair.stamp_ns: pair for pair in pairs}
    for sample in samples:                                  # no averaging: the pairs as they are
        pair = by_stamp[sample.stamp_ns]
        assert sample.link is pair.link and sample.sensor is pair.sensor


def test_config_is_checked():
    with pytest.raises(ValueError, match='capture mode'):
        CaptureConfig(mode='sometimes')
    with pytest.raises(ValueError, match='min_departure_deg'):
        CaptureConfig(min_departure_deg=0.1, rotation_band_deg=0.2)
    with pytest.raises(ValueError, match='positive'):
        CaptureConfig(window_ns=0)


@pytest.mark.parametrize('bare, kept, size', [
    (lambda k: False, True, 1.0), (lambda k: k % 10 == 5, True, 1.0),
    (lambda k: k % 3 == 0, True, 1.0), (lambda k: k % 3 != 0, False, 1.0),
    (lambda k: False, True, 1e308)])   # (their sum overflowed to inf)
def test_a_still_sample_keeps_its_covariance_when_most_frames_have_one(bare, kept, size):
    """One frame without a covariance left the sample without one (the session's all with it)."""
    rng = np.random.default_rng(12)
    link, sensor = Pose.identity(), Pose(np.array([0.1, 0.2, 0.5]), quat.IDENTITY)
    covariance = np.diag([1e-6, 1e-6, 4e-6, 1e-5, 1e-5, 1e-5]) * size * 1e5
    moved = [Pair(k * 10**6, turned(link, 30.0), sensor) for k in range(3)]
    pairs = still_pairs(rng, link, sensor, 10**9, 1.0, 30.0)
    pairs = [Pair(pair.stamp_ns, pair.link, Pose(pair.sensor.position, pair.sensor.quaternion,
                                                 None if bare(k) else covariance))
             for k, pair in enumerate(pairs)]
    (sample,) = run(Capture(CaptureConfig()), moved + pairs)
    if kept:
        assert_allclose(sample.sensor.covariance, covariance)
    else:
        assert sample.sensor.covariance is None
