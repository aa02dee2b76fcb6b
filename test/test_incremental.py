"""
The live calibrator's O(samples) update path equals the batch computations it replaces.

Each incremental piece (appended rotations and positions, extended information, motion
residuals from the samples, the one-step warm-started refinement) is compared with the
batch function on the same data; the whole update is compared with a full solve in
test_calibration.py.
"""

from dataclasses import replace
import gc
import weakref

import numpy as np
import pytest

from quatcal_ros.core import quality
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import Calibrator
from quatcal_ros.core.motions import Motions, pair_indices, SampleRotations
from quatcal_ros.core.refine import refine, refine_from, step_sums
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


@pytest.mark.parametrize('added', [3, 1, 0])
def test_a_step_from_prepared_sums_equals_the_step_over_all_samples(added):
    """Sums made beforehand for the first samples: the same step as linearising all."""
    cell, samples = synthetic(12, 30, rotation_noise_deg=0.3, translation_noise_m=0.001)
    rotations = SampleRotations.from_samples(samples)
    positions = SamplePositions.from_samples(samples, rotations)
    arrays = (rotations.link, positions.link, rotations.sensor, positions.sensor)
    kept = 30 - added
    previous = refine(*(a[:kept] for a in arrays), cell.mounting.quaternion,
                      cell.mounting.position)
    prepared = step_sums(previous, *(a[:kept] for a in arrays))
    assert prepared.count == kept
    at_once = refine_from(previous, *arrays)
    stepped = refine_from(previous, *arrays, prepared=prepared)
    for name in ('quaternion', 'translation', 'object_quaternion', 'object_translation'):
        np.testing.assert_allclose(getattr(stepped, name), getattr(at_once, name), rtol=0,
                                   atol=1e-13)
    for name in ('rotation_noise_deg', 'translation_noise_mm', 'uncertainty_deg',
                 'translation_uncertainty_mm'):
        assert getattr(stepped, name) == pytest.approx(getattr(at_once, name), rel=1e-9)


def test_prepared_updates_equal_unprepared_ones():
    """Calibrator.finish() only moves work earlier: the estimates stay the same."""
    _, samples = synthetic(13, 30, rotation_noise_deg=0.3, translation_noise_m=0.001)
    samples[20] = replace(samples[20], sensor=samples[3].sensor)   # rejected on arrival
    prepared, plain = Calibrator(full_solve_every=100), Calibrator(full_solve_every=100)
    for calibrator in (prepared, plain):
        calibrator.add_samples(samples[:13])
    for sample in samples[13:]:
        assert prepared.finish() == []
        prepared.add_sample(sample)
        plain.add_sample(sample)
        np.testing.assert_allclose(prepared.update.estimate.quaternion,
                                   plain.update.estimate.quaternion, rtol=0, atol=1e-13)
        np.testing.assert_allclose(prepared.update.estimate.translation,
                                   plain.update.estimate.translation, rtol=0, atol=1e-13)
    assert len(prepared.result.rejected) == len(plain.result.rejected) >= 1


def test_incremental_result_matches_a_full_solve_of_the_same_samples():
    """Every field of the incremental result against a full solve that keeps the same inliers."""
    _, samples = synthetic(7, 25, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator(full_solve_every=100, small=12)
    for sample in samples:
        calibrator.add_sample(sample)
    full = Calibrator(full_solve_every=1)
    full.add_samples(samples)
    a, b = calibrator.result, full.result
    assert (a.samples, a.motions, a.inliers, a.inlier_samples) == (
        b.samples, b.motions, b.inliers, b.inlier_samples)
    assert np.degrees(quat.angle_between(a.quaternion, b.quaternion)) < 0.05 * b.uncertainty_deg
    assert a.uncertainty_deg == pytest.approx(b.uncertainty_deg, rel=0.05)
    assert a.residual_rms_deg == pytest.approx(b.residual_rms_deg, rel=0.05)
    assert a.translation_uncertainty_mm == pytest.approx(b.translation_uncertainty_mm, rel=0.05)
    np.testing.assert_allclose(a.closed_form.translation, b.closed_form.translation, atol=1e-4)
    assert a.excitation == pytest.approx(b.excitation, rel=1e-6)


def test_an_update_publishes_before_its_report_is_computed():
    """The estimate is there at once; the quality figures only when first asked for, once."""
    _, samples = synthetic(8, 16, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator(full_solve_every=100, small=12)
    for sample in samples:
        calibrator.add_sample(sample)
    update = calibrator.update
    assert 'result' not in vars(update)            # not computed by the update itself
    result = update.result
    assert update.result is result and calibrator.result is result
    np.testing.assert_array_equal(update.estimate.quaternion, result.quaternion)
    np.testing.assert_array_equal(update.estimate.translation, result.translation)
    assert result.method == 'refined' and result.samples == 16


def test_a_full_solve_due_can_wait_for_finish_and_the_estimates_stay_the_same():
    """Quick update first, full solve on finish(): the same estimates as solving at once."""
    _, samples = synthetic(9, 24, rotation_noise_deg=0.3, translation_noise_m=0.001)
    at_once, later, unfinished = (Calibrator(full_solve_every=5, small=12) for _ in range(3))
    for calibrator in (at_once, later, unfinished):
        calibrator.add_samples(samples[:12])
    for n, sample in enumerate(samples[12:], start=13):
        at_once.add_sample(sample)
        later.add_sample(sample, full_solve_later=True)
        unfinished.add_sample(sample, full_solve_later=True)
        assert later.full_solve_due == (n % 5 == 0) and not at_once.full_solve_due
        if later.full_solve_due:
            quick = later.update
            assert later.finish() == [] and not later.full_solve_due
            assert later.update is not quick
            # The quick update is close to the full solve it precedes.
            full = later.update.estimate
            assert (np.degrees(quat.angle_between(quick.estimate.quaternion, full.quaternion))
                    < 0.1 * full.uncertainty_deg)
        np.testing.assert_array_equal(later.update.estimate.quaternion,
                                      at_once.update.estimate.quaternion)
        np.testing.assert_array_equal(later.update.estimate.translation,
                                      at_once.update.estimate.translation)
        if n % 5 != 0:   # a full solve left due runs first on the next sample
            np.testing.assert_array_equal(unfinished.update.estimate.quaternion,
                                          at_once.update.estimate.quaternion)
    assert later.finish() == []   # nothing due


def test_an_update_lets_the_previous_motion_set_go_once_its_own_exists():
    """The deferred motion set holds the previous one only until it is computed."""
    _, samples = synthetic(14, 14, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator(full_solve_every=100)
    calibrator.add_samples(samples[:13])
    previous = weakref.ref(calibrator._solution.fit())
    calibrator.add_sample(samples[13])
    calibrator.finish()
    gc.collect()
    assert previous() is None
    assert len(calibrator._solution.fit()) == calibrator.result.inliers
