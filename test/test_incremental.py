"""
The O(samples) estimates equal the all-pairs computations they replace, and the live pattern.

The all-pairs least squares of eq. (41) and its information are computed from per-sample sums
(leastsq.all_pairs_rotation, quality.Information.all_pairs): compared here with the motions
formed explicitly. The live calibrator's warm solves between full solves are compared with
full solves of the same samples.
"""

from dataclasses import replace

import numpy as np
import pytest

from quatcal_ros.core import calibration
from quatcal_ros.core import quality
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate, CalibrationOptions, Calibrator
from quatcal_ros.core.leastsq import all_pairs_rotation, b_matrices, hemisphere_signs, \
    least_squares_rotation, MotionSystem, null_vectors
from quatcal_ros.core.motions import Motions, pair_indices, SampleRotations
from quatcal_ros.sim import simulation


def synthetic(seed, n, setup='eye_in_hand', **noise):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng, setup)
    samples, _ = simulation.samples(rng, cell, n, **noise)
    return cell, samples


@pytest.mark.parametrize('setup', ['eye_in_hand', 'eye_to_hand'])
@pytest.mark.parametrize('noise_deg', [0.0, 0.5, 2.0])
def test_all_pairs_rotation_from_sums_equals_the_motions(setup, noise_deg):
    """Top singular vector of sum sigma_i A_i == minimum eigenvector over all motions."""
    for seed in range(5):
        _, samples = synthetic(20 + seed, 40, setup, rotation_noise_deg=noise_deg)
        rotations = SampleRotations.from_samples(samples, setup)
        use = np.ones(len(samples), dtype=bool)
        use[[3, 11]] = False
        kept = np.flatnonzero(use)
        i, j = pair_indices(len(kept))
        motions = Motions.between(rotations, kept[i], kept[j])
        reference = least_squares_rotation(motions.q_a, motions.q_b)
        system = MotionSystem()
        system.add(motions.q_a, motions.q_b, reference=reference)
        expected = system.solve()[0]
        found = all_pairs_rotation(rotations, use, reference)
        # Both are eigenvectors of 4x4 matrices summed from the same data: rounding, 1e-9 deg.
        assert np.degrees(quat.angle_between(found, expected)) < 1e-9


@pytest.mark.parametrize('noise_deg', [0.0, 0.5, 3.0])
def test_two_motion_hypotheses_by_inverse_iteration_equal_the_eigen_solver(noise_deg):
    # The consensus search's hypotheses: the null vector of each pair of motions' eq. (41).
    _, samples = synthetic(11, 12, rotation_noise_deg=noise_deg)
    rotations = SampleRotations.from_samples(samples)
    motions = Motions.between(rotations, *pair_indices(12))
    pairs = np.random.default_rng(2).integers(0, len(motions), (40, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    B = b_matrices(motions.q_a[pairs.ravel()], motions.q_b[pairs.ravel()])
    normals = (np.swapaxes(B, 1, 2) @ B).reshape(len(pairs), 2, 4, 4).sum(axis=1)
    found = null_vectors(normals, least_squares_rotation(motions.q_a, motions.q_b))
    expected = np.linalg.eigh(normals)[1][:, :, 0]
    np.testing.assert_allclose(np.abs(np.einsum('hi,hi->h', found, expected)), 1.0, atol=1e-12)


@pytest.mark.parametrize('spread_deg', [30.0, 170.0])
def test_the_samples_alone_put_their_object_orientations_on_one_hemisphere(spread_deg):
    # Erratum 3's sign of each motion from one anchor sample: sigma_i Z_i all on the side of
    # the true Z, also when the link turns by nearly half a turn between samples.
    for seed in range(10):
        rng = np.random.default_rng(seed)
        cell = simulation.random_cell(rng)
        samples, _ = simulation.samples(rng, cell, 15, rotation_noise_deg=1.0,
                                        rotation_spread_deg=spread_deg)
        rotations = SampleRotations.from_samples(samples)
        Z = rotations.object_orientations(cell.mounting.quaternion)
        signs = hemisphere_signs(rotations.link, rotations.sensor)
        aligned = signs[:, None] * Z
        assert np.all(aligned @ aligned[0] > 0.5)
        reference = all_pairs_rotation(rotations, np.ones(15, bool), cell.mounting.quaternion)
        assert quat.angle_between(all_pairs_rotation(rotations, np.ones(15, bool)),
                                  reference) < 1e-12


def test_all_pairs_information_from_sums_equals_the_motions():
    _, samples = synthetic(5, 30, rotation_noise_deg=0.5)
    rotations = SampleRotations.from_samples(samples)
    use = np.ones(30, dtype=bool)
    use[[0, 17]] = False
    kept = np.flatnonzero(use)
    i, j = pair_indices(len(kept))
    batch = quality.Information.of(rotations.link_matrices, kept[i], kept[j])
    found = quality.Information.all_pairs(rotations.link_matrices, use)
    for name in ('H', 'G', 'C'):
        scale = np.abs(getattr(batch, name)).max()
        np.testing.assert_allclose(getattr(found, name), getattr(batch, name),
                                   atol=1e-12 * scale)


def test_residual_rms_from_samples_matches_the_motions():
    """The all-pairs RMS residual from sample sums against eq. (38) motion by motion."""
    _, samples = synthetic(6, 30, rotation_noise_deg=0.5)
    result = calibrate(samples, CalibrationOptions(method='closed-form'))
    rotations = SampleRotations.from_samples(samples)
    kept = np.flatnonzero(result.sample_ok)
    i, j = pair_indices(len(kept))
    angles = Motions.between(rotations, kept[i], kept[j]).residual_angles(
        result.closed_form.quaternion)
    # First order in the noise: agree to a few percent at 0.5 deg.
    assert result.residual_rms_deg == pytest.approx(np.degrees(np.sqrt(np.mean(angles ** 2))),
                                                    rel=0.03)


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
    # The uncertainties are block jackknives (20 blocks, 19 degrees of freedom: about 16 %
    # scatter of their own); the warm one scales the last full solve's to the new sandwich.
    assert a.uncertainty_deg == pytest.approx(b.uncertainty_deg, rel=0.3)
    assert a.residual_rms_deg == pytest.approx(b.residual_rms_deg, rel=0.05)
    assert a.translation_uncertainty_mm == pytest.approx(b.translation_uncertainty_mm, rel=0.3)
    np.testing.assert_allclose(a.closed_form.translation, b.closed_form.translation, atol=1e-4)
    assert a.excitation == pytest.approx(b.excitation, rel=1e-6)


def test_solve_fully_gives_calibrate_after_warm_solves_and_nothing_new_after_a_full_one():
    """What the node's ~/save asks: its file is then what `solve` of the journal gives."""
    _, samples = synthetic(7, 16, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator(full_solve_every=100, small=12)
    live(calibrator, samples)
    warm = calibrator.result
    calibrator.solve_fully()
    assert calibrator.due and calibrator.estimate() == []
    full = calibrate(samples).to_json_dict()
    assert calibrator.result.to_json_dict() == full != warm.to_json_dict()   # exactly
    calibrator.solve_fully()   # the last estimate was a full one: nothing to do
    assert not calibrator.due


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


def test_a_numerical_failure_keeps_the_earlier_estimate_and_says_so(monkeypatch):
    """The node estimates in a callback: a solver failure must not end the process."""
    _, samples = synthetic(8, 17, rotation_noise_deg=0.3, translation_noise_m=0.001)
    calibrator = Calibrator()
    calibrator.add_samples(samples[:5])
    assert calibrator.estimate() == []
    earlier = calibrator.result

    def fails(*args):
        raise np.linalg.LinAlgError('SVD did not converge')
    monkeypatch.setattr(calibration, '_solve', fails)
    calibrator.add_sample(samples[5])
    assert calibrator.estimate() == ['estimate not updated: the solver failed numerically at 6 '
                                     'samples (SVD did not converge); the earlier estimate '
                                     'stands']
    assert calibrator.result is earlier and not calibrator.due


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
    # The same 15 good samples: the same closed form, to rounding.
    assert np.degrees(quat.angle_between(result.closed_form.quaternion,
                                         results[-1].closed_form.quaternion)) < 1e-9


def test_full_solves_are_spaced_to_a_fifth_of_the_samples():
    calibrator = Calibrator(full_solve_every=10)
    assert [calibrator.full_solve_step(n) for n in (20, 50, 51, 100, 200, 1000)] == \
        [10, 10, 20, 20, 40, 320]
    due = [n for n in range(13, 401) if n % calibrator.full_solve_step(n) == 0]
    assert due[:4] == [20, 30, 40, 50] and 200 in due and 210 not in due
    assert [n for n in due if n > 200] == [240, 320, 400]   # 80 apart beyond 200
