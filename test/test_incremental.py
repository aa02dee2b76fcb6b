"""
The live calibrator's O(samples) update path equals the batch computations it replaces.

Each incremental piece (appended rotations and positions, extended information, motion
residuals from the samples, the one-step warm-started refinement) is compared with the
batch function on the same data; the whole update is compared with a full solve in
test_calibration.py.
"""

from dataclasses import replace

import numpy as np
import pytest

from quatcal_ros.core import quality
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate, Calibrator
from quatcal_ros.core.motions import Motions, pair_indices, SampleRotations
from quatcal_ros.core.refine import refine, refine_from
from quatcal_ros.core.translation import SamplePositions
from quatcal_ros.sim import simulation


def synthetic(seed, n, setup='eye_in_hand', **noise):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng, setup)
    samples, _ = simulation.samples(rng, cell, n, **noise)
    return cell, samples


@pytest.mark.parametrize('setup', ['eye_in_hand', 'eye_to_hand'])
@pytest.mark.parametrize('invert_sensor', [False, True])
def test_appended_samples_equal_the_batch_collection(setup, invert_sensor):
    _, samples = synthetic(1, 9, setup, rotation_noise_deg=0.3, translation_noise_m=0.001)
    rotations = SampleRotations.from_samples(samples[:8], setup, invert_sensor)
    positions = SamplePositions.from_samples(samples[:8], rotations)
    grown = rotations.appended(samples[8])
    batch = SampleRotations.from_samples(samples, setup, invert_sensor)
    np.testing.assert_array_equal(grown.link, batch.link)
    np.testing.assert_array_equal(grown.sensor, batch.sensor)
    np.testing.assert_allclose(grown.link_matrices, quat.matrix_from_quaternion(batch.link),
                               atol=1e-15)
    batch_positions = SamplePositions.from_samples(samples, batch)
    grown_positions = positions.appended(samples[8], grown)
    np.testing.assert_allclose(grown_positions.link, batch_positions.link, atol=1e-15)
    np.testing.assert_allclose(grown_positions.sensor, batch_positions.sensor, atol=1e-15)


def test_extended_information_equals_the_batch_information():
    _, samples = synthetic(2, 12, rotation_noise_deg=0.3)
    rotations = SampleRotations.from_samples(samples)
    i, j = pair_indices(12)
    first = j < 10                               # motions among the first 10 samples
    early = SampleRotations.from_samples(samples[:10])
    info = quality.Information.of(early.link_matrices, i[first], j[first])
    extended = info.extended(rotations.link_matrices, i[~first], j[~first])
    batch = quality.Information.of(rotations.link_matrices, i, j)
    for name in ('H', 'G', 'C'):
        np.testing.assert_allclose(getattr(extended, name), getattr(batch, name), atol=1e-12)
    # A rejected sample adds no motions, only its (zero) row.
    padded = extended.extended(np.concatenate([rotations.link_matrices, np.eye(3)[None]]),
                               [], [])
    assert padded.C.shape == (13, 3, 3) and not padded.C[12].any()
    np.testing.assert_array_equal(padded.H, extended.H)


@pytest.mark.parametrize('noise_deg', [0.5, 1e-7])
def test_motion_residuals_from_samples_equal_eq_38(noise_deg):
    """The same angles as Motions.residual_angles, tiny ones (1e-9 rad) included."""
    cell, samples = synthetic(3, 15, rotation_noise_deg=noise_deg)
    rotations = SampleRotations.from_samples(samples)
    motions = Motions.between(rotations, *pair_indices(15))
    q_z = cell.mounting.quaternion
    expected = motions.residual_angles(q_z)
    found = quality.motion_residual_angles(rotations, q_z, motions.i, motions.j)
    np.testing.assert_allclose(found, expected, rtol=1e-6, atol=1e-15)
    assert expected.max() < 1e-7 or expected.min() > 1e-5   # the two regimes really tested


def test_one_warm_step_lands_within_a_small_fraction_of_the_uncertainty():
    """
    refine_from after one more sample versus a full refinement on the same samples.

    A new sample moves the optimum by about 1/N of the uncertainty's scale; one Gauss-Newton
    step from the old optimum must land within 5 % of the uncertainty of the full answer
    (observed: 1-2 %), far below anything a user could see.
    """
    for seed in range(6):
        cell, samples = synthetic(40 + seed, 31, rotation_noise_deg=[0.1, 0.5, 1.0][seed % 3],
                                  translation_noise_m=0.001)
        rotations = SampleRotations.from_samples(samples)
        positions = SamplePositions.from_samples(samples, rotations)
        arrays = (rotations.link, positions.link, rotations.sensor, positions.sensor)
        start = cell.mounting.quaternion, cell.mounting.position
        previous = refine(*(a[:30] for a in arrays), *start)
        full = refine(*arrays, *start)
        stepped = refine_from(previous, *arrays)
        moved = np.degrees(quat.angle_between(stepped.quaternion, full.quaternion))
        assert moved < 0.05 * full.uncertainty_deg
        assert (1e3 * np.linalg.norm(stepped.translation - full.translation)
                < 0.05 * full.translation_uncertainty_mm)


def live(calibrator, samples):
    """Add samples one by one, estimating after each (the live node); return the results."""
    results = []
    for sample in samples:
        calibrator.add_sample(sample)
        calibrator.estimate()
        results.append(calibrator.result)
    return results


def test_incremental_result_matches_a_full_solve_of_the_same_samples():
    """Every field of the incremental result against a full solve that keeps the same inliers."""
    _, samples = synthetic(7, 25, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator(full_solve_every=100, small=12)
    live(calibrator, samples)
    full = Calibrator(full_solve_every=1)
    full.add_samples(samples)
    full.estimate()
    a, b = calibrator.result, full.result
    assert (a.samples, a.motions, a.inliers, a.inlier_samples) == (
        b.samples, b.motions, b.inliers, b.inlier_samples)
    assert np.degrees(quat.angle_between(a.quaternion, b.quaternion)) < 0.05 * b.uncertainty_deg
    assert a.uncertainty_deg == pytest.approx(b.uncertainty_deg, rel=0.05)
    assert a.residual_rms_deg == pytest.approx(b.residual_rms_deg, rel=0.05)
    assert a.translation_uncertainty_mm == pytest.approx(b.translation_uncertainty_mm, rel=0.05)
    np.testing.assert_allclose(a.closed_form.translation, b.closed_form.translation, atol=1e-4)
    assert a.excitation == pytest.approx(b.excitation, rel=1e-6)


def test_samples_make_an_estimate_due_and_estimate_brings_it_up_to_date():
    _, samples = synthetic(8, 16, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator()
    assert not calibrator.due and calibrator.estimate() == [] and calibrator.result is None
    calibrator.add_samples(samples[:2])
    assert calibrator.due and calibrator.result is None   # nothing estimated yet
    assert calibrator.estimate() == [f'no estimate yet: {calibrator.last_error}']
    assert calibrator.last_error.startswith('2 sample(s): at least 3 are needed')
    calibrator.add_sample(samples[2])
    assert calibrator.estimate() == [] and calibrator.result.samples == 3
    result = calibrator.result
    assert not calibrator.due and calibrator.estimate() == [] and calibrator.result is result
    calibrator.reset()
    assert calibrator.samples == [] and calibrator.result is None and not calibrator.due


def test_the_live_pattern_solves_in_full_on_schedule_and_incrementally_between():
    """
    One estimate per sample: a full solve while few and every full_solve_every-th sample.

    The full solves equal calibrate() on the samples so far; the incremental updates in
    between stay close to it (seen: up to 0.12 of its uncertainty, four steps after a full
    solve).
    """
    _, samples = synthetic(9, 24, rotation_noise_deg=0.3, translation_noise_m=0.001)
    results = live(Calibrator(full_solve_every=5, small=12), samples)
    assert [result.samples for result in results[2:]] == list(range(3, 25))
    for n, result in enumerate(results[2:], start=3):
        full = calibrate(samples[:n])
        if n <= 12 or n % 5 == 0:
            np.testing.assert_array_equal(result.quaternion, full.quaternion)
            np.testing.assert_array_equal(result.translation, full.translation)
            assert result.residual_rms_deg == full.residual_rms_deg
        else:   # an incremental update: not the full solve, but close to it
            assert not np.array_equal(result.quaternion, full.quaternion)
            assert (np.degrees(quat.angle_between(result.quaternion, full.quaternion))
                    < 0.2 * full.uncertainty_deg)


def test_a_rejected_sample_keeps_the_estimate_and_is_reported():
    """A sample that fails the gate on the incremental path: rejected, its motions unused."""
    _, samples = synthetic(13, 20, rotation_noise_deg=0.3, translation_noise_m=0.001)
    samples[15] = replace(samples[15], sensor=samples[3].sensor)   # a bad detection
    calibrator = Calibrator(full_solve_every=100)
    results = live(calibrator, samples[:15])
    calibrator.add_sample(samples[15])
    [message] = calibrator.estimate()
    assert message.startswith('sample 15 rejected: its object orientation disagrees')
    result = calibrator.result
    assert result.samples == 16 and result.inlier_samples == 15
    assert result.inliers == results[-1].inliers and result.motions == 16 * 15 // 2
    assert [r['sample'] for r in result.rejected if 'sample' in r] == [15]
    np.testing.assert_array_equal(result.closed_form.quaternion,
                                  results[-1].closed_form.quaternion)


def test_full_solves_are_spaced_to_a_fifth_of_the_samples():
    calibrator = Calibrator(full_solve_every=10)
    assert [calibrator.full_solve_step(n) for n in (20, 50, 51, 100, 200, 1000)] == \
        [10, 10, 20, 20, 40, 320]
    due = [n for n in range(13, 401) if n % calibrator.full_solve_step(n) == 0]
    assert due[:4] == [20, 30, 40, 50] and 200 in due and 210 not in due
    assert [n for n in due if n > 200] == [240, 320, 400]   # 80 apart beyond 200
