"""The Cramer-Rao bound of the mounting, and the refined estimate's efficiency against it."""

import numpy as np
import pytest
from quatcal_ros.core import bounds
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core import refine
from quatcal_ros.core.calibration import calibrate, CalibrationOptions
from quatcal_ros.core.units import SETUPS
from quatcal_ros.sim import simulation

# Monte-Carlo check: CELLS eye-in-hand cells of SAMPLES samples per noise level. An efficient
# estimator's squared error in cell k has mean tr(C_k) and variance 2 tr(C_k^2) (C_k: that
# cell's bound), so the mean squared error over the cells scatters by
# sqrt(sum 2 tr(C_k^2)) / sum tr(C_k): about 7 % at 150 cells (sqrt(2 / (3 * 150)) = 6.7 % for
# isotropic C_k), i.e. about 3.5 % in the RMS ratio. LOWER = 0.85 (0.72 in mean square) sits
# about 4 of those sigmas below 1: the estimator cannot beat the bound by more than that.
# UPPER = 1.25 allows a modest inefficiency (soft-L1 loss, estimated noise levels, 20 samples);
# the rotation-only closed form is about 1.5x the bound at 0.1 deg / 1 mm and fails it.
CELLS = 150
SAMPLES = 20
LOWER, UPPER = 0.85, 1.25
MAX_SCATTER = 0.09    # the relative scatter of the mean square the band was set for
NOISE_LEVELS = [(0.1, 1e-3), (0.5, 1e-3), (1.0, 1e-3), (0.1, 1e-4)]   # (deg, m) per axis


def monte_carlo(rotation_noise_deg, translation_noise_m, options=CalibrationOptions()):
    """Return squared true errors (rad^2, m^2) and the bound's X blocks for CELLS cells."""
    errors, blocks = [], []
    for k in range(CELLS):
        rng = np.random.default_rng([61, int(rotation_noise_deg * 100),
                                     int(translation_noise_m * 1e4), k])
        cell = simulation.random_cell(rng)
        samples, _ = simulation.samples(rng, cell, SAMPLES,
                                        rotation_noise_deg=rotation_noise_deg,
                                        translation_noise_m=translation_noise_m)
        result = calibrate(samples, options)
        errors.append((quat.angle_between(result.quaternion, cell.mounting.quaternion) ** 2,
                       np.sum((result.translation - cell.mounting.position) ** 2)))
        covariance = bounds.cramer_rao_covariance(
            [s.link.quaternion for s in samples], [s.link.position for s in samples],
            cell.mounting.quaternion, cell.mounting.position,
            cell.target.quaternion, cell.target.position,
            np.radians(rotation_noise_deg), translation_noise_m)
        blocks.append((covariance[0:3, 0:3], covariance[3:6, 3:6]))
    return np.array(errors), blocks


def efficiency(squared_errors, blocks):
    """Return RMS error / RMS bound, and the relative scatter of the bound's mean square."""
    traces = np.array([np.trace(c) for c in blocks])
    scatter = np.sqrt(sum(2.0 * np.trace(c @ c) for c in blocks)) / traces.sum()
    return float(np.sqrt(np.mean(squared_errors) / np.mean(traces))), float(scatter)


@pytest.mark.parametrize('rotation_noise_deg, translation_noise_m', NOISE_LEVELS)
def test_refined_estimate_reaches_the_bound(rotation_noise_deg, translation_noise_m):
    errors, blocks = monte_carlo(rotation_noise_deg, translation_noise_m)
    for axis, name in enumerate(('rotation', 'translation')):
        ratio, scatter = efficiency(errors[:, axis], [b[axis] for b in blocks])
        assert scatter < MAX_SCATTER, f'{name}: too few cells for the band ({scatter:.3f})'
        assert LOWER <= ratio <= UPPER, (
            f'{name} at {rotation_noise_deg} deg / {1e3 * translation_noise_m} mm: RMS error '
            f'{ratio:.3f}x the Cramer-Rao bound, outside [{LOWER}, {UPPER}]')


def test_rotation_only_closed_form_misses_the_bound():
    """The band discriminates: the closed form ignores what positions say about rotation."""
    errors, blocks = monte_carlo(0.1, 1e-3, CalibrationOptions(method='closed-form'))
    ratio, _ = efficiency(errors[:, 0], [b[0] for b in blocks])
    assert ratio > UPPER


@pytest.mark.parametrize('setup', SETUPS)
def test_the_truth_is_where_the_model_holds(setup):
    """The bound's X and O are a cell's mounting and target: refine's model fits them exactly."""
    rng = np.random.default_rng(5)
    cell = simulation.random_cell(rng, setup)
    stops = simulation.stop_poses(rng, cell, 10)
    link_t = np.array([p.position for p in stops])
    link_q = np.array([p.quaternion for p in stops])
    sensor_t, sensor_q = cell.sensor_poses(link_t, link_q)
    if setup == 'eye_to_hand':
        link_t, link_q = simulation.invert(link_t, link_q)
    rotation, translation = refine.residuals(
        link_q, link_t, sensor_q, sensor_t, cell.mounting.quaternion, cell.mounting.position,
        cell.target.quaternion, cell.target.position)
    np.testing.assert_allclose(rotation, 0.0, atol=1e-12)
    np.testing.assert_allclose(translation, 0.0, atol=1e-12)


def half_turns():
    """Return link rotations identity and 180 deg about x, y, z: their matrices sum to zero."""
    return np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])


@pytest.mark.parametrize('sigma_r, sigma_t', [(1e-3, 1e-3), (0.02, 1e-4), (1e-4, 0.05)])
def test_bound_of_a_hand_derived_cell(sigma_r, sigma_t):
    """
    Check the bound against a case solvable by hand.

    With all positions zero the translation residuals do not depend on the rotations, and
    with link rotations summing to zero the fit of O is uncorrelated with that of X: each of
    the N = 4 samples measures X's rotation with std sigma_r and its translation with std
    sigma_t per axis, so both blocks are sigma^2 / N * I, whatever X's and O's rotations.
    """
    rng = np.random.default_rng(3)
    x_q, o_q = simulation.random_quaternions(rng, 2)
    zero = np.zeros(3)
    covariance = bounds.cramer_rao_covariance(half_turns(), np.zeros((4, 3)), x_q, zero, o_q,
                                              zero, sigma_r, sigma_t)
    np.testing.assert_allclose(covariance[0:3, 0:3], sigma_r ** 2 / 4 * np.eye(3),
                               rtol=1e-9, atol=1e-12 * sigma_r ** 2)
    np.testing.assert_allclose(covariance[3:6, 3:6], sigma_t ** 2 / 4 * np.eye(3),
                               rtol=1e-9, atol=1e-12 * sigma_t ** 2)
    assert bounds.rotation_rms_deg(covariance) == pytest.approx(
        np.degrees(sigma_r) * np.sqrt(3 / 4))
    assert bounds.translation_rms_mm(covariance) == pytest.approx(1e3 * sigma_t * np.sqrt(3 / 4))


def test_bound_scales_with_the_noise():
    """Scaling both sigmas by k scales the covariance by k^2; more noise never helps."""
    rng = np.random.default_rng(4)
    cell = simulation.random_cell(rng)
    stops = simulation.stop_poses(rng, cell, 12)
    link_q = [p.quaternion for p in stops]
    link_t = [p.position for p in stops]
    truth = (cell.mounting.quaternion, cell.mounting.position, cell.target.quaternion,
             cell.target.position)

    def bound(sigma_r, sigma_t):
        return bounds.cramer_rao_covariance(link_q, link_t, *truth, sigma_r, sigma_t)

    base = bound(np.radians(0.1), 1e-3)
    np.testing.assert_allclose(bound(np.radians(0.3), 3e-3), 9.0 * base, rtol=1e-8)
    for larger in (bound(np.radians(0.5), 1e-3), bound(np.radians(0.1), 5e-3)):
        assert np.linalg.eigvalsh(larger - base).min() > -1e-12 * np.abs(base).max()
        assert bounds.rotation_rms_deg(larger) > bounds.rotation_rms_deg(base)
        assert bounds.translation_rms_mm(larger) > bounds.translation_rms_mm(base)


def test_jacobian_matches_finite_differences_at_the_truth():
    """The bound's Fisher information rests on refine's Jacobian: check it numerically."""
    rng = np.random.default_rng(6)
    cell = simulation.random_cell(rng)
    stops = simulation.stop_poses(rng, cell, 6)
    link_t = np.array([p.position for p in stops])
    link_q = np.array([p.quaternion for p in stops])
    sensor = cell.sensor_poses(link_t, link_q)
    truth = (cell.mounting.quaternion, cell.mounting.position, cell.target.quaternion,
             cell.target.position)

    def residual(p):
        x_q, x_t, o_q, o_t = truth
        model = (quat.multiply(quat.from_rotation_vector(p[0:3]), x_q), x_t + p[3:6],
                 quat.multiply(quat.from_rotation_vector(p[6:9]), o_q), o_t + p[9:12])
        rotation, translation = refine.residuals(link_q, link_t, sensor[1], sensor[0], *model)
        return np.concatenate([rotation.ravel(), translation.ravel()])

    h = 1e-6
    numeric = np.column_stack([(residual(h * e) - residual(-h * e)) / (2 * h)
                               for e in np.eye(12)])
    analytic = refine.whitened_jacobian(link_q, link_t, *truth, 1.0, 1.0)
    np.testing.assert_allclose(analytic, numeric, atol=1e-7)


@pytest.mark.parametrize('setup', SETUPS)
def test_robot_noise_in_the_sensor_frame_matches_finite_differences(setup):
    """link_noise_covariances is the first-order image of noise on T_base_link: check it."""
    rng = np.random.default_rng(9)
    cell = simulation.random_cell(rng, setup)
    link_t, link_q = (np.array(a) for a in zip(*[(p.position, p.quaternion)
                                                 for p in simulation.stop_poses(rng, cell, 5)]))
    sensor_t, sensor_q = cell.sensor_poses(link_t, link_q)

    def moved(e):   # the sensor poses when every link pose is measured with noise e
        t, q = cell.sensor_poses(link_t + e[3:], quat.multiply(quat.from_rotation_vector(
            np.broadcast_to(e[:3], link_t.shape)), link_q))
        rotation = quat.rotation_vector(quat.multiply(q, quat.conjugate(sensor_q)))
        return np.concatenate([rotation, t - sensor_t], axis=1)   # (N, 6)

    h = 1e-6
    A = np.stack([(moved(h * e) - moved(-h * e)) / (2 * h) for e in np.eye(6)], axis=2)
    link_covariance = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 4e-6, 9e-6])
    refine_t, refine_q = ((link_t, link_q) if setup == 'eye_in_hand'
                          else simulation.invert(link_t, link_q))
    covariances = bounds.link_noise_covariances(
        refine_q, refine_t, cell.mounting.quaternion, cell.target.position, link_covariance,
        setup)
    np.testing.assert_allclose(covariances, A @ link_covariance @ np.transpose(A, (0, 2, 1)),
                               rtol=1e-6, atol=1e-14)
