"""Tests of quatcal_ros.core.drift: noticing a marker or sensor that moved during a session."""

import numpy as np
import pytest
from quatcal_ros.core import calibration
from quatcal_ros.core import drift
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose, Sample
from quatcal_ros.sim import simulation


def cell_and_samples(seed, n, noise_deg=0.2, outlier_fraction=0.0):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, n, rotation_noise_deg=noise_deg,
                                    translation_noise_m=0.001,
                                    outlier_fraction=outlier_fraction)
    return cell, samples


def marker_moved(cell, samples, first, angle_deg, axis=(0.3, 0.5, 0.8)):
    """Return the samples as seen when the object turned by angle_deg from sample `first` on."""
    turn = Pose(np.zeros(3), quat.from_axis_angle(np.asarray(axis) / np.linalg.norm(axis),
                                                  np.radians(angle_deg)))
    moved = []
    for i, s in enumerate(samples):
        if i >= first:
            base_sensor = s.link @ cell.mounting
            s = Sample(s.stamp_ns, s.link, base_sensor.inverse() @ (turn @ base_sensor @ s.sensor))
        moved.append(s)
    return moved


def sensor_slipped(cell, samples, first, angle_deg):
    """Return the samples as seen when the sensor turned on its mount from sample `first` on."""
    slip = Pose(np.zeros(3), quat.from_axis_angle([1.0, 0.0, 0.0], np.radians(angle_deg)))
    return [s if i < first else Sample(s.stamp_ns, s.link, slip.inverse() @ s.sensor)
            for i, s in enumerate(samples)]


@pytest.mark.parametrize('seed', range(8))
def test_no_move_in_good_sessions_even_with_bad_detections(seed):
    cell, samples = cell_and_samples(seed, 40, noise_deg=0.3, outlier_fraction=0.1)
    result = calibration.calibrate(samples)
    assert drift.find_move(samples, result.quaternion) is None


@pytest.mark.parametrize('count', [3, 4, 20])
def test_a_moved_marker_is_found_where_it_moved(count):
    cell, samples = cell_and_samples(3, 12 + count)
    moved = marker_moved(cell, samples, 12, 3.0)
    result = calibration.calibrate(moved)
    move = drift.find_move(moved, result.quaternion)
    assert move is not None and move.first == 12 and move.samples == count
    assert move.before_deg < 0.6 and 2.0 < move.after_deg < 4.0
    assert move.text().startswith(f'the residual rose from {move.before_deg:.2f} to '
                                  f'{move.after_deg:.2f} deg over the last {count} samples')
    assert 'has the marker or the sensor moved? call ~/reset and recollect' in move.text()
    # replay and solve print the same words, where there is no ~/reset
    assert f'(offline: solve the samples from sample {move.first} on, or record again)' in \
        move.text()


def test_two_moved_samples_are_not_yet_a_move():
    cell, samples = cell_and_samples(3, 14)
    moved = marker_moved(cell, samples, 12, 3.0)
    assert drift.find_move(moved, calibration.calibrate(moved).quaternion) is None


def test_the_robust_estimate_alone_does_not_say_what_happened():
    """
    Why the check exists: the robust estimate only down-weights the moved samples as noisy.

    A 3 deg move is no bad detection (the heavy-tailed noise explains it), so nothing is
    rejected; the validation fails, but only the drift check says the marker moved, and when.
    """
    cell, samples = cell_and_samples(3, 16)
    moved = marker_moved(cell, samples, 12, 3.0)
    result = calibration.calibrate(moved)
    assert not result.rejected
    assert {e['sample'] for e in result.noisy} == {12, 13, 14, 15}
    assert result.validation['verdict'] == 'fail'
    assert drift.find_move(moved, result.quaternion).first == 12


def test_a_slipped_sensor_and_noise_free_data():
    cell, samples = cell_and_samples(5, 15, noise_deg=0.2)
    slipped = sensor_slipped(cell, samples, 11, 4.0)
    assert drift.find_move(slipped, calibration.calibrate(slipped).quaternion).first == 11
    cell, clean = cell_and_samples(6, 12, noise_deg=0.0)
    result = calibration.calibrate(clean)
    assert drift.find_move(clean, result.quaternion) is None
    moved = marker_moved(cell, clean, 8, 0.5)
    assert drift.find_move(moved, calibration.calibrate(moved).quaternion).first == 8


def test_first_limits_the_change_points_examined():
    cell, samples = cell_and_samples(3, 20)
    moved = marker_moved(cell, samples, 12, 3.0)
    q = calibration.calibrate(moved).quaternion
    assert drift.find_move(moved[:15], q, first=12).first == 12
    assert drift.find_move(moved, q, first=18) is None      # no change point left (k <= 17)
    assert drift.find_move(moved, q, first=13).first == 13  # all after 13 moved too


@pytest.mark.parametrize('first', [40, 640, 1196, 1197])
def test_a_long_file_is_searched_in_steps_and_finds_the_same_change_point(first):
    # Every change point of a long file cost O(N) each: solve on 8,000 samples took 12 s.
    # Beyond SCANNED change points every step-th is examined, then the earliest between the
    # one found and the one before it: the same change point as examining them all.
    cell, samples = cell_and_samples(77, 1200, noise_deg=0.1)
    q = calibration.calibrate(samples).quaternion
    assert drift.find_move(samples, q) is None
    moved = sensor_slipped(cell, samples, first, 3.0)
    q = calibration.calibrate(moved).quaternion
    Z = calibration.SampleRotations.from_samples(moved).object_orientations(q)
    examined = [k for k in range(drift.MIN_BEFORE, len(moved) - drift.RECENT + 1)
                if drift._move_at(Z, k) is not None]
    assert len(examined) > 0
    assert drift.find_move(moved, q).first == examined[0] == first
