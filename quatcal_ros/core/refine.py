"""
Joint maximum-likelihood refinement of the whole mounting over the absolute poses.

Motion-based methods (the paper's, OpenCV's) use only what pairs of samples say, and the
rotation-only ones ignore what the translations say about the rotation. Here every sample
is compared with one model: the object is fixed, so for sample i (link poses inverted for
eye-to-hand, as in motions.py)
    S_i = inv(X) inv(L_i) O
with X the mounting and O the object pose in the base (eye-to-hand: link) frame. The 12
unknowns (X, O) minimise the squared rotation residuals (radians, sensor frame) over
sigma_r^2 plus the translation residuals (metres) over sigma_t^2. The two noise levels are
re-estimated from the residuals themselves, and a soft-L1 loss tames what outliers survived
the rotation stage. scipy.optimize.least_squares does the minimisation; it starts from the
closed form (Chou-Kamel rotation, closed-form translation), which stays the fallback.
"""

from dataclasses import dataclass

import numpy as np
from quatcal_ros.core import quaternion as quat
from scipy.optimize import least_squares

# Soft-L1 scale in units of the estimated noise: residuals up to ~3 sigma count fully.
ROBUST_SCALE = 3.0
NOISE_ITERATIONS = 3
# Floors of the noise estimates, so exact synthetic data do not divide by zero.
MIN_ROTATION_NOISE = 1e-6      # radians
MIN_TRANSLATION_NOISE = 1e-6   # metres


@dataclass(frozen=True)
class Refinement:
    """The refined mounting X and object pose O, with their uncertainties."""

    quaternion: np.ndarray          # X rotation (w, x, y, z)
    translation: np.ndarray         # X translation, metres
    object_quaternion: np.ndarray
    object_translation: np.ndarray
    rotation_noise_deg: float       # estimated per-axis noise of one sensor orientation
    translation_noise_mm: float     # estimated per-axis noise of one sensor position
    uncertainty_deg: float          # expected RMS error angle of X's rotation
    translation_uncertainty_mm: float
    converged: bool


def residuals(link_q, link_t, sensor_q, sensor_t, x_q, x_t, o_q, o_t, link_R=None):
    """
    Compare measured and predicted sensor poses: rotation (rad) and position (m) errors.

    The prediction is S_i = inv(X) inv(L_i) O (module docstring). The rotation error is the
    rotation vector of inv(q_pred) (x) q_meas = inv(O) (x) L_i (x) X (x) S_i, whose fixed
    factors act as one 4x4 matrix (eq. (11)-(12)); the position error is t_meas minus
    R_X^T w_i, w_i = R_L^T (t_O - t_L) - t_X. link_R: the link rotation matrices, when the
    caller has them (else from link_q).
    """
    return _residuals(link_q, sensor_q, sensor_t, x_q, o_q, quat.matrix_from_quaternion(x_q),
                      _lever(link_q, link_t, x_t, o_t, link_R))


def _residuals(link_q, sensor_q, sensor_t, x_q, o_q, R_X, lever):
    """Return `residuals` given X's rotation matrix and the levers w_i."""
    fixed = quat.plus_matrix(quat.conjugate(o_q)) @ quat.minus_matrix(x_q)
    rotation = quat.rotation_vector(quat.multiply(link_q @ fixed.T, sensor_q))
    return rotation, sensor_t - lever @ R_X


def _lever(link_q, link_t, x_t, o_t, link_R=None):
    """Return w_i = R_L^T (t_O - t_L) - t_X: the object seen from the link, minus X's offset."""
    R_L = quat.matrix_from_quaternion(link_q) if link_R is None else link_R
    return np.einsum('nji,nj->ni', R_L, o_t - link_t) - x_t


def refine(link_q, link_t, sensor_q, sensor_t, x_q, x_t):
    """
    Refine the mounting (x_q, x_t) over samples (link_q, link_t, sensor_q, sensor_t).

    All inputs are arrays of the samples to use (inliers of the rotation stage), link poses
    already inverted for eye-to-hand. Returns a Refinement.
    """
    o_q, o_t = _object_pose(link_q, link_t, sensor_q, sensor_t, x_q, x_t)
    n = len(link_q)
    link_R = quat.matrix_from_quaternion(link_q)
    sigma_r, sigma_t = _noise(*residuals(link_q, link_t, sensor_q, sensor_t, x_q, x_t, o_q,
                                         o_t), n)
    x = np.zeros(12)
    converged = True
    for _ in range(NOISE_ITERATIONS):
        def cost(p, sigma_r=sigma_r, sigma_t=sigma_t):
            model = _unpack(p, x_q, x_t, o_q, o_t)
            return _whitened(*residuals(link_q, link_t, sensor_q, sensor_t, *model, link_R),
                             sigma_r, sigma_t)

        def jacobian(p, sigma_r=sigma_r, sigma_t=sigma_t):
            return whitened_jacobian(link_q, link_t, *_unpack(p, x_q, x_t, o_q, o_t),
                                     sigma_r, sigma_t, link_R)
        fit = least_squares(cost, x, jac=jacobian, loss='soft_l1', f_scale=ROBUST_SCALE,
                            x_scale='jac')
        x = fit.x
        converged = converged and fit.success
        sigma_r, sigma_t = _noise(*residuals(link_q, link_t, sensor_q, sensor_t,
                                             *_unpack(x, x_q, x_t, o_q, o_t)), n)
    model = _unpack(x, x_q, x_t, o_q, o_t)
    whitened, J = _linearised(link_q, link_t, sensor_q, sensor_t, *model, sigma_r, sigma_t,
                              link_R)
    covariance = _inverse(_normal_matrix(J, _soft_l1_weights(whitened)))
    blocks = whitened.reshape(2, -1)
    return _refinement(model, np.einsum('bk,bk->b', blocks, blocks), n, covariance, sigma_r,
                       sigma_t, converged)


def refine_from(previous, link_q, link_t, sensor_q, sensor_t, link_R=None):
    """
    Update a Refinement after samples were added: one warm-started Gauss-Newton step.

    The mounting, the object pose and the noise levels of `previous` are the start; the step
    solves the normal equations of the whitened residuals with the soft-L1 loss as iteratively
    reweighted least squares. Cheap (one linearisation, no line search, no noise
    re-estimation loop): what the live calibrator runs after each new sample between full
    solves. A new sample moves the optimum by a fraction of its uncertainty, and one step
    from that close lands within a few percent of the uncertainty (test_incremental.py). The
    covariance and the noise levels come from the same linearisation (the residuals the step
    predicts), which differs from one at the new point only to second order in the step.
    link_R: the link rotation matrices, when the caller has them.
    """
    model, sigma_r, sigma_t = _start(previous)
    whitened, J = _linearised(link_q, link_t, sensor_q, sensor_t, *model, sigma_r, sigma_t,
                              link_R)
    weights = _soft_l1_weights(whitened)
    covariance = _inverse(_normal_matrix(J, weights))
    step = -covariance @ (J.T @ (weights * whitened))   # the Gauss-Newton step
    predicted = (whitened + J @ step).reshape(2, -1)     # rotation rows, translation rows
    return _refinement(_unpack(step, *model), np.einsum('bk,bk->b', predicted, predicted),
                       len(link_q), covariance, sigma_r, sigma_t,
                       bool(np.all(np.isfinite(step))))


def _start(previous):
    """Return the model (X, O) and the noise levels (floored) of a Refinement."""
    model = (previous.quaternion, previous.translation, previous.object_quaternion,
             previous.object_translation)
    return (model, max(np.radians(previous.rotation_noise_deg), MIN_ROTATION_NOISE),
            max(previous.translation_noise_mm / 1e3, MIN_TRANSLATION_NOISE))


def _linearised(link_q, link_t, sensor_q, sensor_t, x_q, x_t, o_q, o_t, sigma_r, sigma_t,
                link_R=None):
    """Return the whitened residuals (6N: rotations, then translations) and their Jacobian."""
    R_L = quat.matrix_from_quaternion(link_q) if link_R is None else link_R
    R_X = quat.matrix_from_quaternion(x_q)
    lever = _lever(link_q, link_t, x_t, o_t, R_L)
    whitened = _whitened(*_residuals(link_q, sensor_q, sensor_t, x_q, o_q, R_X, lever),
                         sigma_r, sigma_t)
    return whitened, _whitened_jacobian(R_L, R_X, quat.matrix_from_quaternion(o_q), lever,
                                        sigma_r, sigma_t)


def _whitened(rotation, translation, sigma_r, sigma_t):
    """Return the residuals divided by their noise levels, rotations first, as one vector."""
    return np.concatenate([(rotation / sigma_r).ravel(), (translation / sigma_t).ravel()])


def _normal_matrix(J, weights):
    """Return J^T W J with W = diag(weights) (the soft-L1 weights of the residuals)."""
    return J.T @ (weights[:, None] * J)


def _inverse(normal):
    """Return the inverse of a normal matrix; the pseudo-inverse when it is singular."""
    try:
        return np.linalg.inv(normal)
    except np.linalg.LinAlgError:   # degenerate samples: minimum-norm steps
        return np.linalg.pinv(normal)


def _refinement(model, squares, n, covariance, sigma_r, sigma_t, converged):
    """
    Return the Refinement of model (X, O) of n samples, with its residuals and covariance.

    squares: the sums of squares of the whitened rotation and translation residuals, from
    which the noise levels are re-estimated; the covariance is (J^T W J)^-1 of the whitened
    problem with the soft-L1 weights W (whitened with the noise levels the fit used).
    """
    x_q, x_t, o_q, o_t = model
    noise_r, noise_t = _noise_of_squares(sigma_r * sigma_r * squares[0],
                                         sigma_t * sigma_t * squares[1], n)
    return Refinement(
        quaternion=quat.canonical(x_q), translation=x_t, object_quaternion=o_q,
        object_translation=o_t, rotation_noise_deg=float(np.degrees(noise_r)),
        translation_noise_mm=float(1e3 * noise_t),
        uncertainty_deg=float(np.degrees(np.sqrt(max(np.trace(covariance[:3, :3]), 0.0)))),
        translation_uncertainty_mm=float(
            1e3 * np.sqrt(max(np.trace(covariance[3:6, 3:6]), 0.0))),
        converged=bool(converged))


def _soft_l1_weights(whitened):
    """Return the IRLS weights rho'(z) = 1 / sqrt(1 + z) of the soft-L1 loss, z = (r / f)^2."""
    return 1.0 / np.sqrt(1.0 + (whitened / ROBUST_SCALE) ** 2)


def _unpack(p, x_q, x_t, o_q, o_t):
    """Return X and O for parameters p: rotation vectors applied on the left, translations."""
    return (quat.multiply(quat.from_rotation_vector(p[0:3]), x_q), x_t + p[3:6],
            quat.multiply(quat.from_rotation_vector(p[6:9]), o_q), o_t + p[9:12])


def whitened_jacobian(link_q, link_t, x_q, x_t, o_q, o_t, sigma_r, sigma_t, link_R=None):
    """
    Return the whitened residual Jacobian (6N x 12) for left perturbations a, b of X, O.

    link_R: the link rotation matrices, when the caller has them (else from link_q).

    With M = inv(L) O and w = R_L^T (t_O - t_L) - t_X (the object seen from the link, minus
    the mounting offset), to first order:
        rotation residual:     d/da = R_M^T,  d/db = -R_O^T
        translation residual:  d/da = -R_X^T skew(w),  d/dt_X = R_X^T,  d/dt_O = -R_X^T R_L^T
    """
    R_L = quat.matrix_from_quaternion(link_q) if link_R is None else link_R
    return _whitened_jacobian(R_L, quat.matrix_from_quaternion(x_q),
                              quat.matrix_from_quaternion(o_q),
                              _lever(link_q, link_t, x_t, o_t, R_L), sigma_r, sigma_t)


def _whitened_jacobian(R_L, R_X, R_O, w, sigma_r, sigma_t):
    """Return `whitened_jacobian` given the rotation matrices and the levers w_i."""
    n = len(R_L)
    J = np.zeros((2, n, 3, 12))
    J[0, :, :, 0:3] = R_O.T @ R_L / sigma_r
    J[0, :, :, 6:9] = -R_O.T / sigma_r
    J[1, :, :, 0:3] = -R_X.T @ quat.skew(w) / sigma_t
    J[1, :, :, 3:6] = R_X.T / sigma_t
    J[1, :, :, 9:12] = -R_X.T @ np.transpose(R_L, (0, 2, 1)) / sigma_t
    return J.reshape(6 * n, 12)


def _object_pose(link_q, link_t, sensor_q, sensor_t, x_q, x_t):
    """Return the mean object pose O = L_i X S_i over the samples."""
    q = quat.multiply(quat.multiply(link_q, x_q), sensor_q)
    t = link_t + quat.rotate(link_q, x_t + quat.rotate(x_q, sensor_t))
    return quat.average(q), t.mean(axis=0)


def _noise(rotation, translation, n):
    """Return per-axis noise estimates: 3N residuals each, 12 unknowns shared between them."""
    return _noise_of_squares(np.sum(rotation ** 2), np.sum(translation ** 2), n)


def _noise_of_squares(rotation_squares, translation_squares, n):
    """Return `_noise` given the sums of squares of the rotation and translation residuals."""
    dof = max(3 * n - 6, 1)
    return (max(float(np.sqrt(max(rotation_squares, 0.0) / dof)), MIN_ROTATION_NOISE),
            max(float(np.sqrt(max(translation_squares, 0.0) / dof)), MIN_TRANSLATION_NOISE))
