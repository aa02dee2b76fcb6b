"""
Joint maximum-likelihood refinement of the whole mounting over the absolute poses.

Motion-based methods (the paper's, OpenCV's) use only what pairs of samples say, and the
rotation-only ones ignore what the translations say about the rotation. Here every sample
is compared with one model: the object is fixed, so for sample i (link poses inverted for
eye-to-hand, as in motions.py)
    S_i = inv(X) inv(L_i) O
with X the mounting and O the object pose in the base (eye-to-hand: link) frame. The residual
of sample i is 6-D, in the sensor frame: the rotation vector of R_meas R_pred^T (radians) and
t_meas - t_pred (metres). Its noise is a t with a 6x6 scale matrix estimated from the residuals
(heavy_tails.fit_t): anisotropic, as camera poses from PnP are (far noisier along the optical
axis than across it), rotation and translation correlated, and heavy-tailed when the data say
so (nu < inf down-weights noisy samples). Without `robust` the noise is Gaussian: plain
weighted least squares. A few dozen samples cannot estimate 21 covariance entries well, so a
full matrix is used only when the data show its shape clearly; else one variance for rotation
and one for translation (chosen by the information criterion, heavy_tails.fit_t).

The 12 unknowns (X, O) are found by Gauss-Newton in numpy, re-fitting the noise models and
choosing among them again at every step (iteratively reweighted least squares: the answer is
optimal under the noise reported with it; a warm start between full solves keeps its models
and refits their scales); it starts from the closed form (Chou-Kamel rotation, closed-form
translation), which stays the fallback, moved to the Gaussian fit of the residuals linearised
there (_gaussian_start). Every sum is over samples: O(N).

The reported covariance is the sandwich H^-1 B H^-1 (B the scatter of the samples' scores,
with the HC2 small-sample correction; H the Hessian of the negative log-likelihood): it holds
when the model's noise is wrong too, which the model's own H^-1 (`model_covariance`, reported
beside it) does not. H is not the weighted normal matrix A: the t's weights fall as the
residuals grow, so H is A times a curvature below 1 ((nu + d) / (nu + d + 2) for t
residuals, 1 for Gaussian ones; heavy_tails.NoiseFit.curvature, from the fitted weights).
With A in its place the sandwich, the jackknife's steps and the leave-one-out moves came out
short by that factor: with t noise (nu = 3) the true errors were 1.1-1.3x the reported
uncertainty from 20 to 300 samples, 0.9-1.1x with H (1.0x for Gaussian noise either way).
Leave-one-out predictions of every sample come from the same sums (`leave_one_out`).

Samples whose input gave their own covariance C_i are weighted by it: residuals and Jacobian
are whitened by W_i = L_i^-1 (C_i = L_i L_i^T, `sensor_factor`), so the noise model
fits the scale left beyond the given covariances (1 when they are right); `noise_covariance`
carries it back to radians and metres for a typical sample, and `residuals` and
`leave_one_out` stay in radians and metres.
"""

from dataclasses import dataclass, replace
from functools import cached_property, lru_cache
import math

import numpy as np
from quatcal_ros.core import heavy_tails
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.numerics import inverse, rms

MAX_ITERATIONS = 20
# Converged when the last step moved the unknowns by less than this many of their sigmas. The
# reweighted steps shrink 2-3x each under heavy tails (~100x under Gaussian noise), so the
# answer stays up to ~0.01 sigma per axis (0.04 in all 6) from the converged one: < 2e-3 of
# its variance. Measured against a tolerance of 1e-7 (t noise, nu = 3): median 0.005 sigma in
# all 6; at 30 samples none beyond 0.03 of 200 cells, at 8 samples 4 of 300 beyond 0.1 (the
# noise models' probabilities still moving; one cell at another fixed point). Also requiring
# them to settle (within 0.02) left 3 of the 4 and cost an extra step on clean data.
STEP_TOLERANCE = 1e-2
# Floors of the noise estimates, so exact synthetic data do not divide by zero.
MIN_ROTATION_NOISE = 1e-6      # radians
MIN_TRANSLATION_NOISE = 1e-6   # metres
NOISE_FLOOR = np.array([MIN_ROTATION_NOISE] * 3 + [MIN_TRANSLATION_NOISE] * 3) ** 2
# Residuals per sample and the samples' worth of them the 12 unknowns use up.
DIMENSIONS = 6
LOST_SAMPLES = 12 / DIMENSIONS
# The shapes the noise's scale matrix may take: one variance per block (rotation, translation);
# from PER_AXIS_SAMPLES on also one per axis (a camera's depth noise is several times its
# lateral noise: weighed as one, a PnP-like sensor's samples gave errors 2.1-3.9x the
# Cramer-Rao bound at 12-20 samples, per axis 1.2-1.6x; with fewer samples its 4 more
# variances cost isotropic noise 15-20 % of accuracy at 6 samples for PnP-like noise's
# 25 % gain, 2-9 % against 31-43 % at 8); a full 6x6 one only from FULL_SHAPE_SAMPLES samples
# on (fitted to fewer, its 21 entries follow the noise of the few: a nearly singular matrix
# that weighs some directions without bound and reports a far too small uncertainty).
BLOCK_SHAPES = (heavy_tails.isotropic_blocks(DIMENSIONS),)
DIAGONAL_SHAPES = BLOCK_SHAPES + (heavy_tails.diagonal(DIMENSIONS),)
SHAPES = DIAGONAL_SHAPES + (heavy_tails.full(DIMENSIONS),)
PER_AXIS_SAMPLES = 8
FULL_SHAPE_SAMPLES = 30
# Weighted steps on the linearised model that start the refinement (_gaussian_start).
GAUSSIAN_START_ITERATIONS = 3
# Blocks of the jackknife (_jackknife), and the floats a batch of its replicates may hold
# (2 MB: all 20 at once up to about 170 samples; a long replay's final solve stays small).
JACKKNIFE_BLOCKS = 20
JACKKNIFE_BATCH_FLOATS = 250_000
# Up to this many samples the per-sample block products are kept (_Sums: 288 floats each).
GRAM_SAMPLES = JACKKNIFE_BATCH_FLOATS // 288


class ReportedUncertainty:
    """The uncertainty figures of an estimate whose `reported_covariance` is X's 6 x 6."""

    @property
    def uncertainty_deg(self):
        """Return the expected RMS error angle of X's rotation (degrees), as reported."""
        return uncertainties(self.reported_covariance)[0]

    @property
    def translation_uncertainty_mm(self):
        """Return the expected RMS error of X's translation (millimetres), as reported."""
        return uncertainties(self.reported_covariance)[1]


@dataclass(frozen=True)
class Refinement(ReportedUncertainty):
    """The refined mounting X and object pose O, their covariance and the fitted noise."""

    quaternion: np.ndarray          # X rotation (w, x, y, z)
    translation: np.ndarray         # X translation, metres
    object_quaternion: np.ndarray
    object_translation: np.ndarray
    noise: heavy_tails.NoiseFit     # of the 6-D sensor-frame residuals (rad, m)
    covariance: np.ndarray          # 12 x 12 sandwich: X rotation, X translation, O, O
    model_covariance: np.ndarray    # 12 x 12 inverse weighted normal matrix
    residuals: np.ndarray           # (N, 6) at the answer
    leave_one_out: np.ndarray       # (N, 6) each sample's residual predicted without it
    converged: bool
    resampled: np.ndarray = None    # 6 x 6 block-jackknife covariance of X (_jackknife)
    resampled_from_earlier: bool = False   # scaled from an earlier jackknife (with_jackknife_of)
    whitening: np.ndarray = None    # (N, 6, 6) W_i from the samples' own covariances, or None

    @cached_property
    def noise_covariance(self):
        """
        Return the fitted noise of one sensor pose (6x6, rad and m; a typical sample's).

        With the samples' own covariances, that of a sample of their mean information: the
        inverse of the mean of the inverses, which weigh the samples in the estimate too.
        Their plain mean was the largest one's (a sample that says it knows nothing, a
        variance of 1 m^2 among millimetres, made the noise reported 22 deg and 285 mm where
        the samples scatter by 0.2 deg and 1 mm; the estimate rightly gives it no weight).
        """
        if self.whitening is None:
            return self.noise.covariance
        # C_i^-1 = W_i^T S^-1 W_i, S the fitted scale in whitened coordinates
        information = (np.transpose(self.whitening, (0, 2, 1)) @ inverse(self.noise.covariance)
                       @ self.whitening)
        covariance = inverse(information.mean(axis=0))
        covariance.flags.writeable = False   # remembered: callers share it
        return covariance

    @property
    def rotation_noise_deg(self):
        """Return the per-axis RMS rotation noise of one sensor pose (degrees)."""
        return float(np.degrees(np.sqrt(np.trace(self.noise_covariance[:3, :3]) / 3.0)))

    @property
    def translation_noise_mm(self):
        """Return the per-axis RMS translation noise of one sensor pose (millimetres)."""
        return float(1e3 * np.sqrt(np.trace(self.noise_covariance[3:, 3:]) / 3.0))

    @property
    def reported_covariance(self):
        """Return X's 6 x 6 covariance as reported: resampled when it was, else the sandwich."""
        return self.covariance[:6, :6] if self.resampled is None else self.resampled


def uncertainties(covariance):
    """
    Return X's expected RMS errors (rotation angle in degrees, translation in millimetres).

    covariance: a covariance whose first six rows and columns are X's rotation (radians) and
    translation (metres): Refinement.covariance (the sandwich), .model_covariance or
    .reported_covariance.
    """
    return float(np.degrees(rms(covariance[:3, :3]))), 1e3 * rms(covariance[3:6, 3:6])


def residuals(link_q, link_t, sensor_q, sensor_t, x_q, x_t, o_q, o_t, link_R=None):
    """
    Compare measured and predicted sensor poses: rotation (rad) and position (m) errors.

    The prediction is S_i = inv(X) inv(L_i) O (module docstring). The rotation error is the
    rotation vector of q_meas (x) inv(q_pred) = S_i (x) inv(O) (x) L_i (x) X, in the sensor
    frame; the fixed factors inv(O) and X act on L_i as one 4x4 matrix (eq. (11)-(12)). The
    position error is t_meas minus R_X^T w_i, w_i = R_L^T (t_O - t_L) - t_X. link_R: the
    link rotation matrices, when the caller has them (else from link_q).
    """
    samples = _Samples(link_q, link_t, sensor_q, sensor_t, link_R)
    e = samples.errors((x_q, x_t, o_q, o_t))[0]
    return e[:, :3], e[:, 3:]


def lever(link_q, link_t, x_t, o_t, link_R=None):
    """Return w_i = R_L^T (t_O - t_L) - t_X: the object seen from the link, minus X's offset."""
    R_L = quat.matrix_from_quaternion(link_q) if link_R is None else link_R
    return np.einsum('nji,nj->ni', R_L, o_t - link_t) - x_t


def jacobian(R_L, R_X, w):
    """
    Return the residual Jacobian (N, 6, 12) for left perturbations a, b of X and O.

    With w = R_L^T (t_O - t_L) - t_X (the object seen from the link, minus the mounting
    offset), to first order:
        rotation residual:     d/da = R_X^T,  d/db = -R_X^T R_L^T
        translation residual:  d/da = -R_X^T skew(w),  d/dt_X = R_X^T,  d/dt_O = -R_X^T R_L^T
    """
    return _jacobian(R_L, R_X, w @ R_X)


def _jacobian(R_L, R_X, u):
    """Return `jacobian` given u = R_X^T w (the predicted sensor position)."""
    J = np.zeros((len(R_L), 6, 12))
    R_X_T = R_X.T
    to_sensor = R_X_T @ np.swapaxes(R_L, 1, 2)
    J[:, 0:3, 0:3] = R_X_T
    J[:, 0:3, 6:9] = -to_sensor
    # R_X^T skew(w) = skew(R_X^T w) R_X^T
    J[:, 3:6, 0:3] = -quat.skew(u) @ R_X_T
    J[:, 3:6, 3:6] = R_X_T
    J[:, 3:6, 9:12] = J[:, 0:3, 6:9]
    return J


def whitened_jacobian(link_q, link_t, x_q, x_t, o_q, o_t, sigma_r, sigma_t, link_R=None):
    """
    Return the Jacobian (6N x 12) of the residuals divided by their noise levels.

    Rows: all rotation residuals, then all translation residuals; sigma_r (radians) and
    sigma_t (metres) per axis. link_R: the link rotation matrices, when the caller has them.
    """
    R_L = quat.matrix_from_quaternion(link_q) if link_R is None else link_R
    J = jacobian(R_L, quat.matrix_from_quaternion(x_q), lever(link_q, link_t, x_t, o_t, R_L))
    J[:, 0:3] /= sigma_r
    J[:, 3:6] /= sigma_t
    return np.concatenate([J[:, 0:3].reshape(-1, 12), J[:, 3:6].reshape(-1, 12)])


class _Samples:
    """The samples of a refinement, with what every step needs of them computed once."""

    def __init__(self, link_q, link_t, sensor_q, sensor_t, link_R=None, whitening=None):
        self.link_q = np.asarray(link_q, dtype=float)
        self.link_R = quat.matrix_from_quaternion(self.link_q) if link_R is None else link_R
        self.link_origin = np.einsum('nji,nj->ni', self.link_R, link_t)   # R_L^T t_L
        # S_i (x) inv(O) (x) L_i (x) X is bilinear in inv(O) and X: T_i (inv(O) X^T).ravel(),
        # with T_i = P+(S_i) [e_j (x) L_i (x) e_k]_jk (eq. (11)-(12)); stacked (4N, 16).
        n = len(self.link_q)
        between = (self.link_q @ _UNIT_PRODUCTS).reshape(n, 4, 16)
        self.rotation_terms = (quat.plus_matrix(sensor_q) @ between).reshape(-1, 16)
        self.sensor_t = np.asarray(sensor_t, dtype=float)
        self.whitening = whitening

    def __len__(self):
        return len(self.link_q)

    def errors(self, model):
        """Return the residuals (N, 6) at model (X, O), R_X and u = R_X^T w (residuals())."""
        x_q, x_t, o_q, o_t = model
        R_X = quat.matrix_from_quaternion(x_q)
        fixed = np.outer(quat.conjugate(o_q), x_q).ravel()            # inv(O) X^T
        measured = (self.rotation_terms @ fixed).reshape(-1, 4)
        u = (o_t @ self.link_R - self.link_origin - x_t) @ R_X     # R_X^T w
        e = np.empty((len(u), 6))
        e[:, :3] = quat.rotation_vector(measured)
        e[:, 3:] = self.sensor_t - u
        return e, R_X, u

    def linearised(self, model):
        """Return the residuals (N, 6: rotation, translation) and their Jacobian (N, 6, 12)."""
        e, R_X, u = self.errors(model)
        J = _jacobian(self.link_R, R_X, u)
        if self.whitening is None:
            return e, J
        return (self.whitening @ e[..., None])[..., 0], self.whitening @ J


# e_j (x) q (x) e_k = P+(e_j) P-(e_k) q for the unit quaternions e_j, e_k: q @ _UNIT_PRODUCTS
# holds component a of each at [a, (j, k)] (4 x 64).
_UNIT_PRODUCTS = np.einsum('jab,kbc->cajk', quat.plus_matrix(np.eye(4)),
                           quat.minus_matrix(np.eye(4))).reshape(4, 64)


def refine(link_q, link_t, sensor_q, sensor_t, x_q, x_t, robust=True, start=None,
           max_iterations=MAX_ITERATIONS, sensor_factor=None, resample=False,
           object_start=None, link_R=None):
    """
    Refine the mounting (x_q, x_t) over samples (link_q, link_t, sensor_q, sensor_t).

    All inputs are arrays of the samples to use (the good ones of the rotation stage), link
    poses already inverted for eye-to-hand. robust: a heavy-tailed noise model (else
    Gaussian); start: an earlier Refinement to start from instead (a warm start: its mounting
    and object pose, and its noise models and their probabilities, whose scales alone are
    refitted; a solve without it chooses the models); sensor_factor: (N, 6, 6) the lower
    Cholesky factor L_i of each sample's own covariance of its residual (C_i = L_i L_i^T;
    rotation, translation: pose.residual_order), or None; resample: add the block jackknife
    (_jackknife); object_start: the object pose (quaternion, position) the samples give with
    (x_q, x_t), when the caller has it (else object_pose); link_R: the link rotation
    matrices, when the caller has them. Returns a Refinement.
    """
    whitening = None if sensor_factor is None else whitening_of(sensor_factor)
    samples = _Samples(link_q, link_t, sensor_q, sensor_t, link_R, whitening)
    if start is None:
        o_q, o_t = (object_pose(link_q, link_t, sensor_q, sensor_t, x_q, x_t, samples.link_R)
                    if object_start is None else object_start)
        x_q, x_t, o_q, o_t = _gaussian_start(samples, (x_q, x_t, o_q, o_t))
    else:
        x_q, x_t = start.quaternion, start.translation
        o_q, o_t = start.object_quaternion, start.object_translation
    model, noise, converged, (e, J) = _fit(samples, (x_q, x_t, o_q, o_t), robust,
                                           start.noise if start is not None else None,
                                           max_iterations)
    return _refinement(model, _Sums(e, J, noise), noise, converged, whitening, resample)


def _gaussian_start(samples, model, iterations=GAUSSIAN_START_ITERATIONS):
    """
    Return the model moved to the Gaussian fit of the residuals linearised at it.

    The closed form weighs rotations and translations by their own least squares, so the
    refinement's first steps mostly find their relative weight: one variance per block of the
    residuals (rotation, translation), refitted on the linear prediction e + J dx after each
    weighted step, settles it on the linearised model at no cost of relinearising or fitting
    the heavy-tailed models, which then start from residuals near the answer. On the linear
    model each block's sum of squares is S_b + 2 dx.g_b + dx^T G_b dx (G_b = J_b^T J_b,
    g_b = J_b^T e_b): every step is 12 x 12 arithmetic.
    """
    e, J = samples.linearised(model)
    rows = np.swapaxes(J.reshape(len(J), 2, 3, 12), 0, 1).reshape(2, -1, 12)   # (2, 3N, 12)
    residuals = np.swapaxes(e.reshape(-1, 2, 3), 0, 1).reshape(2, -1)         # (2, 3N)
    gram = np.swapaxes(rows, 1, 2) @ rows                                 # (2, 12, 12)
    gradient = (np.swapaxes(rows, 1, 2) @ residuals[..., None])[..., 0]   # (2, 12)
    squares = np.einsum('bk,bk->b', residuals, residuals)                 # (2,)
    scale = 1.0 / (3.0 * max(len(e) - LOST_SAMPLES, 1.0))
    step = np.zeros(12)
    for _ in range(iterations):
        predicted = squares + 2.0 * gradient @ step + (gram @ step) @ step
        information = 1.0 / (predicted * scale + NOISE_FLOOR[::3])          # (2,)
        step = -_solve((information @ gram.reshape(2, -1)).reshape(12, 12),
                       information @ gradient)
    return apply_step(step, *model) if np.all(np.isfinite(step)) else model


def whitening_of(factors):
    """Return W_i = L_i^-1 (module docstring) of the covariances' Cholesky factors (N, 6, 6)."""
    return np.linalg.inv(np.asarray(factors, dtype=float))


def _fit(samples, model, robust, warm, max_iterations):
    """
    Return the refined model (X, O), the noise model at it and whether the steps converged.

    And the residuals and Jacobian (e, J) at the model.

    samples: the _Samples; warm: a NoiseFit of similar residuals to start the noise models'
    EM from, or None.
    Gauss-Newton steps, each under the noise models chosen again from the residuals it starts
    from (their EM warm-started from the last fit: iteratively reweighted least squares), until
    a step moves the unknowns by less than STEP_TOLERANCE of their sigmas (the noise fitted
    before it then stands at the answer too); else the noise is fitted at the last model.
    Given `warm`, its models stay and only their scales and weights follow the steps.
    """
    grid = heavy_tails.NU_GRID if robust else (math.inf,)
    shapes = (SHAPES if len(samples) >= FULL_SHAPE_SAMPLES else
              DIAGONAL_SHAPES if len(samples) >= PER_AXIS_SAMPLES else BLOCK_SHAPES)

    def noise_at(e, noise):
        if warm is not None:
            return noise.refitted(e, LOST_SAMPLES, NOISE_FLOOR)
        return heavy_tails.fit_t(e, shapes, grid, LOST_SAMPLES, NOISE_FLOOR, start=noise)

    noise = warm
    last = None
    for _ in range(max_iterations):
        e, J = samples.linearised(model)
        noise = noise_at(e, noise)
        A, g = _normal_equations(J, e, noise)
        step = -_solve(A, g)
        if not np.all(np.isfinite(step)):
            break
        size = float(step @ A @ step)   # in sigmas, squared
        if size < STEP_TOLERANCE ** 2:   # the noise stands at the answer
            model = apply_step(step, *model)
            # (e, J) at the answer to first order in the step (below 1 % of a sigma)
            return model, noise, True, (e + J @ step, J)
        model = apply_step(_extrapolated(step, last, A, size), *model)
        last = step
    e, J = samples.linearised(model)
    return model, noise_at(e, noise), False, (e, J)


def _extrapolated(step, last, A, size):
    """
    Return the step to take: `step`, or its geometric tail when the steps shrink steadily.

    Each refit of the noise moves the optimum by a fraction r of the last step, so the steps
    of reweighted least squares shrink geometrically along one direction: when this step and
    the last point the same way (cosine above 0.95 in A's metric) and shrank by r < 0.9, the
    fixed point lies about step / (1 - r) away. The plain step decides convergence.
    """
    if last is None:
        return step
    previous = float(last @ A @ last)
    if previous <= 0.0:
        return step
    ratio = math.sqrt(size / previous)
    cosine = float(step @ A @ last) / math.sqrt(size * previous)
    return step / (1.0 - ratio) if cosine > 0.95 and ratio < 0.9 else step


class _Sums:
    """
    The residuals e (N, 6) and Jacobian J (N, 6, 12) at an answer, and their per-sample parts.

    Noise models of isotropic blocks (heavy_tails.NoiseFit.block: three residuals, or one
    when the noise is per axis) give each sample one information per block, so every normal
    matrix the estimate, its leave-one-out and its jackknife form is a weighted sum of the same
    per-sample block products J_ib^T J_ib and J_ib^T e_ib (`gram`, `gradient`): formed once,
    each sum is one product (up to GRAM_SAMPLES samples; else, and for full scale matrices,
    from e and J).
    """

    def __init__(self, e, J, noise):
        self.e, self.J = e, J
        self.blocks = noise.block is not None and len(e) <= GRAM_SAMPLES
        if self.blocks:
            size = noise.block
            blocks = J.reshape(len(J), -1, size, J.shape[2])             # (N, 6 / size, size, 12)
            self.gram = np.swapaxes(blocks, 2, 3) @ blocks               # (N, 6 / size, 12, 12)
            self.gradient = np.einsum('nbri,nbr->nbi', blocks, e.reshape(len(e), -1, size))

    def normal_equations(self, information, diagonal):
        """
        Return A (..., 12, 12) and g (..., 12) of informations (..., N, 6, 6).

        Given as their diagonals (..., N, 6) with `diagonal`, as one per block (..., N, 2)
        when `blocks`.
        """
        if self.blocks:
            flat = information.reshape(information.shape[:-2] + (-1,))   # (..., 2N)
            A = (flat @ self.gram.reshape(-1, 144)).reshape(flat.shape[:-1] + (12, 12))
            return A, flat @ self.gradient.reshape(-1, 12)
        MJ = _weighed(information, self.J, diagonal)
        MJ = MJ.reshape(MJ.shape[:-3] + (-1, 12))                        # (..., 6N, 12)
        return self.J.reshape(-1, 12).T @ MJ, np.swapaxes(MJ, -1, -2) @ self.e.reshape(-1)


def _jackknife(noise, sums, curvature, blocks=JACKKNIFE_BLOCKS):
    """
    Return the block-jackknife covariance of X given the noise and the _Sums at the answer.

    curvature: the noise's (NoiseFit.curvature), each step's Hessian over its normal matrix.

    The samples (in their order, so that neighbours in time fall together) are cut into
    `blocks` contiguous blocks; without each, the noise models' scales and weights are
    re-fitted to the other samples' residuals and one Newton step from the answer (its
    Hessian the module docstring's H) gives that replicate's mounting (the step from an
    optimum this close lands within a small fraction of the uncertainty). The spread of
    those answers is what the sandwich cannot see: the noise model's own estimation from the
    same residuals, which makes the fitted weights look better than they are with a few
    dozen samples. Cost: `blocks` steps, O(N) each. None with fewer than 3 samples.
    """
    e = sums.e
    n = len(e)
    count = min(blocks, n)
    if count < 3:
        return None
    keep = _kept_samples(n, count)
    diagonal = noise.diagonal
    moves = []
    # Replicates in batches of a bounded size (each holds its (N, 6, 12) weighted Jacobian).
    batch = count if sums.blocks else max(1, JACKKNIFE_BATCH_FLOATS // (n * 6 * 12))
    for start in range(0, count, batch):
        rows = keep[start:start + batch]
        information = noise.refitted_information_blocks(e, rows, LOST_SAMPLES, NOISE_FLOOR,
                                                        per_block=sums.blocks)
        A, g = sums.normal_equations(information, diagonal)
        moves.append(-_solve(A, g)[:, :6] / curvature)               # X's rotation, translation
    moves = np.concatenate(moves) if len(moves) > 1 else moves[0]
    centred = moves - moves.mean(axis=0)
    return (count - 1) / count * centred.T @ centred


@lru_cache(maxsize=8)
def _kept_samples(n, count):
    """
    Return which samples each of `count` jackknife replicates keeps, (count, n) bool, read-only.

    Contiguous blocks as np.array_split cuts them: the first n % count one sample longer.
    """
    sizes = np.full(count, n // count)
    sizes[:n % count] += 1
    keep = np.repeat(np.arange(count), sizes)[None, :] != np.arange(count)[:, None]
    keep.flags.writeable = False
    return keep


def _weighed(information, J, diagonal):
    """Return M_i J_i for informations (..., N, 6, 6), or their diagonals (..., N, 6)."""
    return information[..., None] * J if diagonal else information @ J


def with_jackknife_of(refinement, earlier):
    """
    Return `refinement` with a resampled covariance scaled from an earlier one's jackknife.

    Between full solves (one more sample) the jackknife's excess over the sandwich changes
    little: each block of X's covariance (rotation, translation) is the sandwich scaled by
    the ratio the jackknife of `earlier` (a Refinement of nearly the same samples) had to
    its sandwich. Cost: nothing; the next full solve resamples again.
    """
    if earlier is None or earlier.resampled is None:
        return refinement
    scale = []
    for block in (slice(0, 3), slice(3, 6)):
        sandwich = np.trace(earlier.covariance[block, block])
        ratio = np.trace(earlier.resampled[block, block]) / sandwich if sandwich > 0 else 1.0
        scale += [np.sqrt(ratio)] * 3
    scale = np.array(scale)
    return replace(refinement, resampled=refinement.covariance[:6, :6] * np.outer(scale, scale),
                   resampled_from_earlier=True)


def _information(noise):
    """Return each sample's information and whether it is given by its diagonals (N, 6)."""
    diagonal = noise.information_diagonal()
    return (noise.information(), False) if diagonal is None else (diagonal, True)


def _normal_equations(J, e, noise):
    """Return A = sum J_i^T M_i J_i and g = sum J_i^T M_i e_i, M_i the samples' information."""
    information, diagonal = _information(noise)
    MJ = _weighed(information, J, diagonal).reshape(-1, J.shape[2])    # M_i J_i: (6N, 12)
    return J.reshape(MJ.shape).T @ MJ, MJ.T @ e.reshape(-1)


def _solve(normal, rhs):
    """Return normal^-1 rhs: one system (12, 12), (12,) or a batch (B, 12, 12), (B, 12)."""
    try:
        return np.linalg.solve(normal, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:   # degenerate samples: a minimum-norm step
        return (np.linalg.pinv(normal) @ rhs[..., None])[..., 0]


def _refinement(model, sums, noise, converged, whitening=None, resample=False):
    """
    Return the Refinement of model (X, O) with the _Sums at it and the noise.

    e and J whitened by `whitening` when it is given; the residuals reported are not.
    resample: with the block jackknife (_jackknife).
    """
    x_q, x_t, o_q, o_t = model
    e, J = sums.e, sums.J
    information, diagonal = _information(noise)
    curvature = noise.curvature(DIMENSIONS)   # H = curvature A (module docstring)
    if sums.blocks:
        weights = noise.information_per_block()
        n = len(weights)
        per_sample = (weights[:, None, :] @ sums.gram.reshape(n, -1, 144)).reshape(n, 12, 12)
        held = (weights[:, None, :] @ sums.gradient)[:, 0]               # J_i^T M_i e_i
    else:
        WJ = np.swapaxes(_weighed(information, J, diagonal), 1, 2)       # (N, 12, 6)
        per_sample, held = WJ @ J, (WJ @ e[..., None])[..., 0]
    A = per_sample.sum(axis=0)
    A_inv = inverse(A)
    leave_one_out = _leave_one_out(A, per_sample, held / curvature, J, e)
    H_inv = A_inv / curvature
    sandwich = H_inv @ _score_scatter(J, e, information, diagonal, A_inv) @ H_inv
    if whitening is not None:   # back to radians and metres
        unwhiten = np.linalg.inv(whitening)
        e = (unwhiten @ e[..., None])[..., 0]
        leave_one_out = (unwhiten @ leave_one_out[..., None])[..., 0]
    return Refinement(
        quaternion=quat.canonical(x_q), translation=x_t, object_quaternion=o_q,
        object_translation=o_t, noise=noise, covariance=sandwich,
        model_covariance=A_inv / noise.efficiency(DIMENSIONS), residuals=e,
        leave_one_out=leave_one_out, converged=bool(converged),
        resampled=_jackknife(noise, sums, curvature) if resample else None,
        whitening=whitening)


def _score_scatter(J, e, information, diagonal, A_inv):
    """
    Return B = sum_i s_i s_i^T, the scatter of the samples' scores, for the sandwich.

    The plain residuals of a fit with 12 unknowns understate the noise, the more for the
    samples that steer the fit: in whitened coordinates (M_i = L_i L_i^T) each residual's
    covariance is I - h_i, h_i = L_i^T J_i A^-1 J_i^T L_i its block of the hat matrix, so it
    is divided by a root of I - h_i (the HC2 correction, unbiased for a linear model with the
    noise the weights assume): s_i = J_i^T L_i K_i^-1 L_i^T e_i with K_i K_i^T = I - h_i
    (Cholesky; the symmetric root where I - h_i is singular). information: (N, 6, 6), or with
    `diagonal` its diagonals (N, 6).
    """
    if diagonal:   # L_i = sqrt(M_i)
        root = np.sqrt(information)
        whitened_J = root[..., None] * J
        whitened_e = (root * e)[..., None]
    else:
        L_T = np.swapaxes(np.linalg.cholesky(information), 1, 2)   # (N, 6, 6)
        whitened_J = L_T @ J
        whitened_e = L_T @ e[..., None]
    whitened_J_T = np.swapaxes(whitened_J, 1, 2)
    left = np.eye(J.shape[1]) - whitened_J @ A_inv @ whitened_J_T       # I - h_i
    try:
        corrected = np.linalg.solve(np.linalg.cholesky(left), whitened_e)
    except np.linalg.LinAlgError:   # a sample the fit passes through: I - h_i singular
        values, vectors = np.linalg.eigh(left)
        root = (vectors / np.sqrt(np.maximum(values, 1e-12))[:, None, :]) @ np.swapaxes(
            vectors, 1, 2)
        corrected = root @ whitened_e
    scores = (whitened_J_T @ corrected)[..., 0]
    return scores.T @ scores


def _leave_one_out(A, per_sample, held, J, e):
    """
    Return each sample's residual predicted by the fit of all the other samples (N, 6).

    Removing sample k moves the optimum by (A - J_k^T W_k J_k)^-1 J_k^T W_k e_k (one
    Gauss-Newton step, exact for a linear model; the caller divides `held` by the
    curvature for the Hessian's A), and its residual by J_k times that.
    per_sample: J_k^T W_k J_k (N, 12, 12); held: J_k^T W_k e_k (N, 12).
    """
    without = A - per_sample
    try:
        moved = np.linalg.solve(without, held[..., None])
    except np.linalg.LinAlgError:   # a sample the others cannot do without
        moved = np.linalg.pinv(without) @ held[..., None]
    return e + (J @ moved)[..., 0]


def apply_step(p, x_q, x_t, o_q, o_t):
    """Return X and O moved by p: rotation vectors applied on the left, translations added."""
    return (quat.normalize(quat.multiply(quat.from_rotation_vector(p[0:3]), x_q)), x_t + p[3:6],
            quat.normalize(quat.multiply(quat.from_rotation_vector(p[6:9]), o_q)),
            o_t + p[9:12])


def object_pose(link_q, link_t, sensor_q, sensor_t, x_q, x_t, link_R=None):
    """Return the mean object pose O = L_i X S_i over the samples."""
    q = quat.multiply(quat.multiply(link_q, x_q), sensor_q)
    R_L = quat.matrix_from_quaternion(link_q) if link_R is None else link_R
    in_link = x_t + sensor_t @ quat.matrix_from_quaternion(x_q).T    # X S_i's position
    t = link_t + (R_L @ in_link[..., None])[..., 0]
    return quat.average(q), t.mean(axis=0)
