"""
The mounting from the target's pixels: a joint maximum-likelihood fit on corner residuals.

The unknowns are refine.py's: the mounting X and the board pose O (T_base_board for
eye-in-hand, T_link_board for eye-to-hand; link poses as refine gets them). View i sees
board corner p at the pixel camera.project(R_S p + t_S), S_i = inv(X) inv(L_i) O; the
residual is the detected pixel minus that. Gauss-Newton over the 12 unknowns (left rotation
vectors and translations, as refine's), with Huber weights on each corner's residual (robust
to a few bad corners) and the pixel noise from Huber's proposal-2 scale (each residual
clipped at the Huber threshold, so bad corners cannot inflate it: the weighted residuals'
RMS grew with the bad corners' size, 3.6x the true noise with 3 % of corners 30 px off); the
Jacobian by central differences of the vectorised model (every corner of every view at once).
The intrinsics stay fixed; their misfit shows as a pixel noise above the detector's.

Uncertainty: the sandwich with blocks of views as clusters (each block's score, leverage
corrected as HC2 does: (I - H_bb)^-1/2, H_bb the block's part of the hat matrix), which sees
what the model cannot (errors shared by a view's corners), with the model's
sigma^2 (J^T W J)^-1 reported beside it. Without the correction (a leave-block-out
jackknife) each block's large share of the leverage made it cautious: true error / reported
0.61-0.65 at 8 views, 0.8 at 15. With it, from MIN_BLOCK_VIEWS views on. Below, the model's
alone, which cannot see a view's shared errors: with the robot's pose off by 0.1-0.3 deg and
0.5-1 mm per view, true error / model 6-10x at 5-7 synthetic views, 4.7-5.4x on halves (7
views) of a real ChArUco recording; over the views' blocks 0.80-1.24x at 6-7 synthetic views
(test_vision.py's cells and another 40 of each), 1.14-1.62x at 5, 1.23-1.29x on those real
halves. `cramer_rao_covariance` is the bound for independent Gaussian pixel noise.
"""

from dataclasses import dataclass

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.motions import SampleRotations
from quatcal_ros.core.refine import apply_step, object_pose, ReportedUncertainty, \
    uncertainties
from quatcal_ros.core.translation import SamplePositions

MAX_ITERATIONS = 30
STEP_TOLERANCE = 1e-6          # in units of the unknowns' sigmas
HUBER_SIGMAS = 2.5             # corners beyond this many sigmas are down-weighted
VIEW_BLOCKS = 20
MIN_BLOCK_VIEWS = 6            # fewer views: the model's covariance (module docstring)
DIFFERENCE_STEP = 1e-7         # radians and metres


@dataclass(frozen=True)
class Corners:
    """Every corner of the views used, stacked: view index, board point, detected pixel."""

    view: np.ndarray     # (K,) int
    points: np.ndarray   # (K, 3) board frame, metres
    pixels: np.ndarray   # (K, 2)

    @staticmethod
    def of(views):
        """Stack (object_points, image_points) of each view."""
        return Corners(np.concatenate([np.full(len(o), i) for i, (o, _) in enumerate(views)]),
                       np.concatenate([o for o, _ in views]).astype(float),
                       np.concatenate([u for _, u in views]).astype(float))


@dataclass(frozen=True)
class ReprojectionFit(ReportedUncertainty):
    """The mounting X and board pose O on pixels, their covariance, the pixel noise."""

    quaternion: np.ndarray
    translation: np.ndarray
    object_quaternion: np.ndarray
    object_translation: np.ndarray
    pixel_noise_px: float
    rms_px: float
    model_covariance: np.ndarray   # 12 x 12
    resampled: np.ndarray          # 6 x 6 of X over blocks of views, or None (too few views)
    converged: bool
    iterations: int
    view_rms_px: np.ndarray        # (N,) RMS residual of each view

    @property
    def reported_covariance(self):
        """Return X's 6 x 6 covariance as reported: over the views' blocks, else the model's."""
        return self.model_covariance[:6, :6] if self.resampled is None else self.resampled

    def to_json_dict(self):
        """Return the JSON object of the fit (the "reprojection" key of `solve DIR`)."""
        model = uncertainties(self.model_covariance[:6, :6])
        return {'rotation': quat.xyzw_json(self.quaternion),
                'translation': quat.xyz_json(self.translation),
                'uncertainty_deg': float(self.uncertainty_deg),
                'translation_uncertainty_mm': float(self.translation_uncertainty_mm),
                'uncertainty_from': ('view_blocks' if self.resampled is not None
                                     else 'model'),
                'model_uncertainty_deg': float(model[0]),
                'model_translation_uncertainty_mm': float(model[1]),
                'pixel_noise_px': float(self.pixel_noise_px),
                'reprojection_rms_px': float(self.rms_px),
                'worst_view_rms_px': float(np.max(self.view_rms_px)),
                'converged': bool(self.converged), 'iterations': int(self.iterations)}


def predicted_pixels(link_q, link_t, corners, camera, model):
    """Return the pixels (K, 2) the model (X, O) predicts for every corner."""
    x_q, x_t, o_q, o_t = model
    R_X, R_O = quat.matrix_from_quaternion(x_q), quat.matrix_from_quaternion(o_q)
    R_L = quat.matrix_from_quaternion(link_q)                       # (N, 3, 3)
    R_S = R_X.T @ np.transpose(R_L, (0, 2, 1)) @ R_O                 # (N, 3, 3)
    t_S = (np.einsum('nji,nj->ni', R_L, o_t - link_t) - x_t) @ R_X   # (N, 3)
    v = corners.view
    points = np.einsum('kij,kj->ki', R_S[v], corners.points) + t_S[v]
    return camera.project(points)


def jacobian(link_q, link_t, corners, camera, model):
    """Return d pixels / d unknowns, (K, 2, 12), by central differences."""
    columns = []
    for k in range(12):
        step = np.zeros(12)
        step[k] = DIFFERENCE_STEP
        plus = predicted_pixels(link_q, link_t, corners, camera, apply_step(step, *model))
        minus = predicted_pixels(link_q, link_t, corners, camera, apply_step(-step, *model))
        columns.append((plus - minus) / (2 * DIFFERENCE_STEP))
    return np.stack(columns, axis=-1)


def refine_reprojection(link_q, link_t, views, camera, x_q, x_t, o_q, o_t, robust=True,
                        max_iterations=MAX_ITERATIONS):
    """
    Fit X and O to the corners of `views` ([(object_points, image_points)], one per link pose).

    Starts from (x_q, x_t, o_q, o_t), e.g. the pose-based refinement's answer; returns a
    ReprojectionFit.
    """
    link_q, link_t = np.asarray(link_q, dtype=float), np.asarray(link_t, dtype=float)
    corners = Corners.of(views)
    model = (np.asarray(x_q, float), np.asarray(x_t, float), np.asarray(o_q, float),
             np.asarray(o_t, float))
    converged, iterations = False, 0
    for iterations in range(1, max_iterations + 1):
        e = corners.pixels - predicted_pixels(link_q, link_t, corners, camera, model)
        J = jacobian(link_q, link_t, corners, camera, model)
        w, sigma = _weights(e, robust)
        A, g = _normal_equations(J, e, w)
        step = np.linalg.lstsq(A, g, rcond=None)[0]
        model = apply_step(step, *model)
        if float(step @ A @ step) / sigma ** 2 < STEP_TOLERANCE ** 2:
            converged = True
            break
    e = corners.pixels - predicted_pixels(link_q, link_t, corners, camera, model)
    J = jacobian(link_q, link_t, corners, camera, model)
    w, sigma = _weights(e, robust)
    A, _ = _normal_equations(J, e, w)
    A_inv = np.linalg.pinv(A)
    squared = np.sum(e * e, axis=1)
    view_rms = np.sqrt(np.bincount(corners.view, squared) / np.bincount(corners.view))
    return ReprojectionFit(
        quaternion=quat.canonical(model[0]), translation=model[1], object_quaternion=model[2],
        object_translation=model[3], pixel_noise_px=sigma,
        rms_px=float(np.sqrt(squared.mean())), model_covariance=sigma ** 2 * A_inv,
        resampled=_view_blocks(J, e, w, A_inv, corners.view, len(views)), converged=converged,
        iterations=iterations, view_rms_px=view_rms)


def refine_from_poses(samples, views, camera, result, setup='eye_in_hand', robust=True):
    """
    Return the ReprojectionFit started from a pose-based CalibrationResult of `samples`.

    views: [(object_points, image_points)] of each sample's image; the samples the result
    used (sample_ok) are fitted, from its mounting and the mean object pose it implies.
    """
    rotations = SampleRotations.from_samples(samples, setup)
    positions = SamplePositions.from_samples(samples, rotations)
    used = np.asarray(result.sample_ok, dtype=bool)
    link_q, link_t = rotations.link[used], positions.link[used]
    o_q, o_t = object_pose(link_q, link_t, rotations.sensor[used], positions.sensor[used],
                           result.quaternion, result.translation)
    return refine_reprojection(link_q, link_t, [v for v, ok in zip(views, used) if ok], camera,
                               result.quaternion, result.translation, o_q, o_t, robust=robust)


# E[min(r^2, c^2)] / 2 for a 2-D Gaussian residual of unit sigma per axis (r^2 ~ chi2 with 2
# degrees of freedom, an exponential of mean 2): Huber's proposal 2 divides by it.
HUBER_SCALE_FACTOR = 1.0 - np.exp(-0.5 * HUBER_SIGMAS ** 2)
SCALE_ITERATIONS = 10


def _weights(e, robust):
    """Return each corner's Huber weight and the pixel noise sigma (per axis)."""
    r = np.linalg.norm(e, axis=1)
    dof = max(e.size - 12, 1)
    if not robust:
        return np.ones(len(r)), max(float(np.sqrt(np.sum(r * r) / dof)), 1e-6)
    sigma = max(float(np.median(r)) / 1.1774, 1e-6)   # the median of a 2-D Gaussian's norm
    for _ in range(SCALE_ITERATIONS):   # proposal 2: sigma^2 = sum min(r, c sigma)^2 / (b dof)
        clipped = np.minimum(r, HUBER_SIGMAS * sigma)
        sigma = max(float(np.sqrt(np.sum(clipped * clipped) / (HUBER_SCALE_FACTOR * dof))),
                    1e-6)
    return np.minimum(1.0, HUBER_SIGMAS * sigma / np.maximum(r, 1e-12)), sigma


def _normal_equations(J, e, w):
    WJ = J * w[:, None, None]
    flat_WJ, flat_J = WJ.reshape(-1, 12), J.reshape(-1, 12)
    return flat_WJ.T @ flat_J, flat_WJ.T @ e.reshape(-1)


def _view_blocks(J, e, w, A_inv, view, n_views):
    """
    Return X's covariance over blocks of views (module docstring), or None with too few views.

    A^-1 (sum_b s_b s_b^T) A^-1 with s_b = J_b^T W_b^1/2 (I - H_bb)^-1/2 W_b^1/2 e_b, the
    block's whitened residuals corrected by the root of I - H_bb (symmetric, by eigenvalues);
    A_inv: the (pseudo-)inverse of the weighted normal matrix of J, e, w.
    """
    if n_views < MIN_BLOCK_VIEWS:
        return None
    scatter = np.zeros((12, 12))
    for block in np.array_split(np.arange(n_views), min(VIEW_BLOCKS, n_views)):
        rows = np.isin(view, block)
        root_w = np.sqrt(np.repeat(w[rows], 2))
        J_b = J[rows].reshape(-1, 12) * root_w[:, None]
        e_b = e[rows].reshape(-1) * root_w
        values, vectors = np.linalg.eigh(np.eye(len(e_b)) - J_b @ A_inv @ J_b.T)
        corrected = vectors @ ((vectors.T @ e_b) / np.sqrt(np.maximum(values, 1e-6)))
        score = J_b.T @ corrected
        scatter += np.outer(score, score)
    return (A_inv @ scatter @ A_inv)[:6, :6]


def cramer_rao_covariance(link_q, link_t, views, camera, model, sigma_px):
    """Return the 12 x 12 bound sigma^2 (J^T J)^-1 at the true model, pixel noise sigma_px."""
    corners = Corners.of(views)
    J = jacobian(np.asarray(link_q, float), np.asarray(link_t, float), corners, camera,
                 tuple(np.asarray(m, float) for m in model)).reshape(-1, 12)
    return sigma_px ** 2 * np.linalg.inv(J.T @ J)
