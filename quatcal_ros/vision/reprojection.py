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
Jacobian analytic, every corner of every view at once (pixels_and_jacobians).
The intrinsics stay fixed; their misfit shows as a pixel noise above the detector's.

Errors all corners of a view share (the robot's pose error, a focal length off) are a
random board pose error per view in the camera frame, rotation and translation, with 6
variances D fitted with the pixel noise by EM (ViewNoise); the Gauss-Newton steps then weigh
each view by its covariance sigma^2 W^-1 + G D G^T (G: the pixels' Jacobian of that error,
by the Woodbury identity, _ViewSums). The fit without them (D = 0) is kept when the corners
do not show them: twice the log-likelihood ratio below VIEW_ERROR_EVIDENCE (on 60 synthetic
cells of 6-8 views without them, at most 6.2; with the robot off by 0.03 deg and 0.1 mm,
median 24). With the robot's pose off by 0.2 deg and 1 mm, 8-16 synthetic views, 30 cells
each, the views' errors took the rotation error from 1.07-0.64 deg to 0.48-0.26 (as the
pose-based fit's or better) and the translation from 4.7-3.3 mm to 3.2-1.8; without them
the views' corners counted as independent.

A focal length off in camera_info moves every view's board in depth; the robot's motions
tell the true depths, so a scale of the focal lengths (the principal point kept) is a 13th
unknown when the corners show it: twice the log-likelihood ratio at least FOCAL_EVIDENCE and
the scale FOCAL_SIGMAS of its standard deviations over the views from 1, from MIN_FOCAL_VIEWS
views on (on a real recording's 7-view halves, whose views' errors inflate the likelihood,
the likelihood alone fitted 0.98-1.02 in 3 of 12, both tests 0.974 and 1.0125 in 2 of 40).
With the robot off by 0.2 deg and 1 mm, the focal lengths 2 % off took the translation error
from 12.4 to 2.1 mm at 16 synthetic views and 11.7 to 2.5 at 12 (error / reported
0.91-1.14); on 68 cells of 12-16 views without a focal error the statistic was at most 6.7.

Uncertainty, with the views' errors: a jackknife over blocks of views with the noise fitted
again without each (_view_jackknife). The sandwich alone missed the noise model's own
estimation from a few views: true error / reported 1.44 at 10 synthetic views; the
jackknife 0.64-1.21 at 6-16 (cautious at 6-7, where each view left out holds much of the
leverage), 0.80-1.16 on rendered folders of 6-16 views, 0.81 and 0.91 on halves (7 views)
of a real ChArUco recording.
Without them: the sandwich with blocks of views as clusters (each block's score, leverage
corrected as HC2 does: (I - H_bb)^-1/2, H_bb the block's part of the hat matrix), which sees
what the model cannot (errors shared by a view's corners), with the model's
sigma^2 (J^T W J)^-1 reported beside it. Without the correction (a leave-block-out
jackknife) each block's large share of the leverage made it cautious: true error / reported
0.61-0.65 at 8 views, 0.8 at 15. With it, from MIN_BLOCK_VIEWS views on. Below, the model's
alone. `cramer_rao_covariance` is the bound for independent Gaussian pixel noise.
"""

from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.motions import SampleRotations
from quatcal_ros.core.refine import apply_step, object_pose, ReportedUncertainty, \
    uncertainties
from quatcal_ros.core.translation import SamplePositions
from quatcal_ros.vision.detect import board_pose, pose_jacobian

MAX_ITERATIONS = 30
STEP_TOLERANCE = 1e-6          # in units of the unknowns' sigmas
HUBER_SIGMAS = 2.5             # corners beyond this many sigmas are down-weighted
VIEW_BLOCKS = 20
MIN_BLOCK_VIEWS = 6            # fewer views: the model's covariance (module docstring)
START_VIEW_ERROR = 1e-3        # the views' shared errors' start (rad, m): EM cannot leave 0
NOISE_ITERATIONS = 200         # EM steps of the noise fit, at most
NOISE_TOLERANCE = 1e-2         # ... until -log L falls by less (the test below: 11.2 in -log L)
EVIDENCE_TOLERANCE = 1e-4      # ... a round's gain in -log L, for the tests' maximum likelihood
VARIANCE_FLOOR = 1e-12         # px^2
NOISE_REFITS = 8               # Gauss-Newton steps that refit the noise, then it stays
# The views' errors are fitted when twice the log-likelihood ratio exceeds chi^2 of 6 degrees
# of freedom at 0.999 (a test at the boundary, D = 0: conservative); below, without them.
VIEW_ERROR_EVIDENCE = 22.46
# The focal scale is fitted when twice its log-likelihood ratio exceeds chi^2 of 1 degree of
# freedom at 0.999, and it lies this many of its standard deviations over the views (the
# jackknife's, or the blocks' without the views' errors) from 1; else camera_info's stand.
FOCAL_EVIDENCE = 10.83
FOCAL_SIGMAS = 3.29
# ... tested from this many views on: on 7-view halves of a real recording two of 40 fitted
# 0.974 and 1.0125, each 5 of its standard deviations from 1. (The standard deviation over
# the views needs MIN_BLOCK_VIEWS of them.)
MIN_FOCAL_VIEWS = 10
assert MIN_FOCAL_VIEWS >= MIN_BLOCK_VIEWS


@dataclass(frozen=True)
class ViewNoise:
    """
    The pixels' noise model: each corner's own, and each view's shared board pose error.

    pixel_variance: px^2 per axis (divided by a corner's Huber weight); view_sd: (6,) standard
    deviations of the view's board pose error, x y z in the camera frame: a turn about the
    board's origin (rotation vector, rad), then a shift (m). That is the robot's pose error
    as the camera sees it, and the camera model's (a focal length off moves every view in
    depth), approximately: the variances are independent, so a turn of the robot's link,
    which also moves the board by its lever arm, shows as both.
    """

    pixel_variance: float
    view_sd: np.ndarray


@dataclass(frozen=True)
class Corners:
    """Every corner of the views used, stacked: view index, board point, detected pixel."""

    view: np.ndarray     # (K,) int
    points: np.ndarray   # (K, 3) board frame, metres
    pixels: np.ndarray   # (K, 2)

    @staticmethod
    def of(views):
        """Stack (object_points, image_points) of each view, in order (_ViewSums needs it)."""
        for i, (points, _) in enumerate(views):
            if len(points) == 0:
                raise ValueError(f'view {i} has no corners')
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
    model_covariance: np.ndarray   # 12 x 12 (13 x 13 with the focal scale)
    resampled: np.ndarray          # 6 x 6 of X over the views, or None (too few views)
    converged: bool
    iterations: int
    view_rms_px: np.ndarray        # (N,) RMS residual of each view
    within_view_rms_px: float      # RMS residual less each view's shared error (its estimate)
    view_error: np.ndarray         # (6,) ViewNoise.view_sd of the fit, zeros without
    view_error_evidence: float = None   # 2 log-likelihood ratio of the views' errors (tested)
    focal_scale: float = 1.0       # camera_info's focal lengths times this (fitted, else 1)
    focal_scale_sd: float = None   # its standard deviation, when fitted
    focal_evidence: float = None   # 2 log-likelihood ratio of fitting it (tested)
    held_out: 'HeldOut' = None     # what the fit without each view predicts of it
    leave_one_out: np.ndarray = None   # (N, 6) its sensor pose's errors (refine_from_poses)

    @property
    def model(self):
        """Return (X's quaternion, translation, O's quaternion, translation)."""
        return (self.quaternion, self.translation, self.object_quaternion,
                self.object_translation)

    @property
    def views_share_errors(self):
        """Return whether the fit models each view's shared error (VIEW_ERROR_EVIDENCE)."""
        return bool(np.any(self.view_error > 0))

    @property
    def uncertainty_from(self):
        """Return what the reported uncertainty is: view_jackknife, view_blocks or model."""
        if self.resampled is None:
            return 'model'
        return 'view_jackknife' if self.views_share_errors else 'view_blocks'

    @property
    def reported_covariance(self):
        """Return X's 6 x 6 covariance as reported: over the views, else the model's."""
        return self.model_covariance[:6, :6] if self.resampled is None else self.resampled

    def to_json_dict(self):
        """Return the JSON object of the fit (the "reprojection" key of `solve DIR`)."""
        model = uncertainties(self.model_covariance[:6, :6])
        return {'rotation': quat.xyzw_json(self.quaternion),
                'translation': quat.xyz_json(self.translation),
                'uncertainty_deg': float(self.uncertainty_deg),
                'translation_uncertainty_mm': float(self.translation_uncertainty_mm),
                'uncertainty_from': self.uncertainty_from,
                'model_uncertainty_deg': float(model[0]),
                'model_translation_uncertainty_mm': float(model[1]),
                'pixel_noise_px': float(self.pixel_noise_px),
                'view_error_deg': [float(v) for v in np.degrees(self.view_error[:3])],
                'view_error_mm': [float(v) for v in 1e3 * self.view_error[3:]],
                'view_error_evidence': (None if self.view_error_evidence is None
                                        else float(self.view_error_evidence)),
                'reprojection_rms_px': float(self.rms_px),
                'worst_view_rms_px': float(np.max(self.view_rms_px)),
                'within_view_rms_px': float(self.within_view_rms_px),
                'view_error_threshold': VIEW_ERROR_EVIDENCE,
                'focal_scale': float(self.focal_scale),
                'focal_scale_sd': (None if self.focal_scale_sd is None
                                   else float(self.focal_scale_sd)),
                'focal_evidence': (None if self.focal_evidence is None
                                   else float(self.focal_evidence)),
                'focal_threshold': FOCAL_EVIDENCE,
                'converged': bool(self.converged), 'iterations': int(self.iterations)}


@dataclass(frozen=True)
class HeldOut:
    """What the fit without each view predicts of it: its sensor pose and its corners."""

    quaternion: np.ndarray   # (N, 4) the board's orientation in the camera frame
    translation: np.ndarray  # (N, 3) its position there (m)
    rms_px: np.ndarray       # (N,) RMS of the view's corners from their predicted pixels

    def errors(self, sensor_q, sensor_t):
        """
        Return the observed sensor poses' errors from the predicted ones (N, 6).

        As refine's residuals: a rotation vector (rad), then a position (m), sensor frame.
        """
        errors = np.empty((len(self.rms_px), 6))
        errors[:, :3] = quat.rotation_vector(quat.multiply(sensor_q,
                                                           quat.conjugate(self.quaternion)))
        errors[:, 3:] = sensor_t - self.translation
        return errors


def board_in_camera(link_q, link_t, model):
    """Return each view's board pose in the camera frame S = inv(X) inv(L) O: R (N, 3, 3), t."""
    _, M, R_O, t_S = _camera_frame(link_q, link_t, model)
    return M @ R_O, t_S


def _camera_frame(link_q, link_t, model):
    """Return R_X, M = R_X^T R_L^T (N, 3, 3), R_O and each view's t_S (N, 3)."""
    x_q, x_t, o_q, o_t = model
    R_X, R_O = quat.matrix_from_quaternion(x_q), quat.matrix_from_quaternion(o_q)
    R_L = quat.matrix_from_quaternion(link_q)                       # (N, 3, 3)
    M = R_X.T @ np.transpose(R_L, (0, 2, 1))                         # (N, 3, 3)
    t_S = (np.einsum('nji,nj->ni', R_L, o_t - link_t) - x_t) @ R_X   # (N, 3)
    return R_X, M, R_O, t_S


def predicted_pixels(link_q, link_t, corners, camera, model):
    """Return the pixels (K, 2) the model (X, O) predicts for every corner."""
    R_S, t_S = board_in_camera(link_q, link_t, model)
    v = corners.view
    points = np.einsum('kij,kj->ki', R_S[v], corners.points) + t_S[v]
    return camera.project(points)


def pixels_and_jacobians(link_q, link_t, corners, camera, model, shared=True):
    """
    Return the pixels (K, 2) the model predicts and their Jacobians (analytic).

    d pixels / d unknowns (K, 2, 12), and d pixels / d (view error) (K, 2, 6) when `shared`
    (else None). With c = R_S p + t_S each corner in the camera frame and M = R_X^T R_L^T:
    the unknowns move as apply_step moves them (rotation vectors a of X and o of O on the
    left, shifts b of x_t and d of o_t), so dc/da = [c]x R_X^T, dc/db = -R_X^T,
    dc/do = -[R_S p]x M, dc/dd = M; the view error turns S by a rotation vector on the left
    and shifts it in the camera frame (ViewNoise.view_sd's coordinates): -[R_S p]x and I.
    Each is chained with the camera's d pixels / dc (Camera.project_with_jacobian).
    """
    R_X, M, R_O, t_S = _camera_frame(link_q, link_t, model)
    v = corners.view
    M_v = M[v]
    turned = np.einsum('kij,kj->ki', M_v @ R_O, corners.points)      # R_S p, (K, 3)
    c = turned + t_S[v]
    pixels, P = camera.project_with_jacobian(c)                      # P: (K, 2, 3)
    G = pose_jacobian(P, turned)                                      # (K, 2, 6)
    # a row r of P times [w]x is (r x w)^T; G's first block is -P [R_S p]x
    J = np.concatenate([np.cross(P, c[:, None, :]) @ R_X.T, -P @ R_X.T, G[..., :3] @ M_v,
                        P @ M_v], axis=2)
    return pixels, J, (G if shared else None)


def jacobian(link_q, link_t, corners, camera, model):
    """Return d pixels / d unknowns, (K, 2, 12) (pixels_and_jacobians)."""
    return pixels_and_jacobians(link_q, link_t, corners, camera, model, shared=False)[1]


class _ViewSums:
    """
    Each view's weighted sums of its corners' Jacobians and residuals.

    J: of the unknowns (None: the sums of the noise's likelihood alone), G: of the view's
    error (None: no view error), e: the residuals, for the view's covariance
    C = sigma^2 W^-1 + G D G^T. The corners come view by view, as Corners.of stacks them.

    Every product with C^-1 goes through the Woodbury identity with the 6 x 6
    B = I + D^1/2 G^T P G D^1/2 (P = W / sigma^2): no corner-sized matrix is formed.
    """

    def __init__(self, J, G, e, w, view):
        starts = np.flatnonzero(np.r_[True, np.diff(view) != 0])

        def per_view(terms):
            return np.add.reduceat(terms, starts, axis=0)
        views = len(starts)
        if J is not None:
            wJ = J * w[:, None, None]
            self.JWJ = per_view(np.einsum('kai,kaj->kij', wJ, J))
            self.JWe = per_view(np.einsum('kai,ka->ki', wJ, e))
            self.JWG = (np.zeros((views, J.shape[2], 6)) if G is None else
                        per_view(np.einsum('kai,kaj->kij', wJ, G)))
        if G is None:
            self.GWG, self.GWe = np.zeros((views, 6, 6)), np.zeros((views, 6))
        else:
            wG = G * w[:, None, None]
            self.GWG = per_view(np.einsum('kai,kaj->kij', wG, G))
            self.GWe = per_view(np.einsum('kai,ka->ki', wG, e))
        self.eWe = per_view(np.einsum('ka,ka->k', e * w[:, None], e))
        self.count = per_view(np.full(len(w), 2.0))
        self.log_w = per_view(2.0 * np.log(w))

    def of_views(self, keep):
        """Return the sums of the views `keep` (a boolean mask or indices) alone."""
        part = object.__new__(_ViewSums)
        for name, sums in vars(self).items():
            setattr(part, name, sums[keep])
        return part

    def _woodbury(self, noise):
        d = noise.view_sd
        B = np.eye(6) + d[:, None] * self.GWG * d / noise.pixel_variance
        return d, np.linalg.inv(B), d * self.GWe / noise.pixel_variance

    def view_errors(self, noise):
        """Return each view's error given its corners (the posterior mean), (N, 6)."""
        d, B_inv, u = self._woodbury(noise)
        return d * np.einsum('vij,vj->vi', B_inv, u)

    def negative_log_likelihood(self, noise, woodbury=None):
        """
        Return -log L of the residuals under `noise` (constant terms left out).

        woodbury: _woodbury(noise), when the caller has it.
        """
        _, B_inv, u = self._woodbury(noise) if woodbury is None else woodbury
        quadratic = self.eWe / noise.pixel_variance - np.einsum('vi,vij,vj->v', u, B_inv, u)
        log_det = (self.count * np.log(noise.pixel_variance) - self.log_w
                   - np.linalg.slogdet(B_inv)[1])
        return 0.5 * float(np.sum(quadratic + log_det))

    def fit_noise(self, noise, unknowns_per_variance=2, tolerance=NOISE_TOLERANCE):
        """
        Return the ViewNoise fitted from `noise` by EM.

        The views' errors are the missing data: each step sets every variance to its mean
        given the corners (the posterior mean squared plus the posterior variance), summed
        over the views less `unknowns_per_variance` (the 12 unknowns move the views' board
        poses as 2 views' errors do, a correction for a few views, with which EM is no longer
        sure to raise the likelihood: it stops when it does not); 0: maximum likelihood.
        """
        last = np.inf
        woodbury = self._woodbury(noise)
        for _ in range(NOISE_ITERATIONS):
            before = noise
            noise = self._em_step(woodbury, unknowns_per_variance)
            woodbury = self._woodbury(noise)
            value = self.negative_log_likelihood(noise, woodbury)
            if value > last:
                return before
            if last - value < tolerance:
                break
            last = value
        return noise

    def maximum_likelihood_noise(self, noise, tolerance=EVIDENCE_TOLERANCE):
        """
        Return the ViewNoise of maximum likelihood from `noise`: EM with squared extrapolation.

        Where a variance tends to zero, EM crawls (the likelihood-ratio tests' fits took the
        most of NOISE_ITERATIONS steps, 80 % of a 20-view fit's EM). Each round takes two EM
        steps, extrapolates along them in the variances' logarithms (SQUAREM, Varadhan and
        Roland 2008, its third scheme; logarithms keep the variances positive), and one EM
        step from there; when that step is less likely than the second plain one, the plain
        one is kept, so the likelihood never falls. Until a round gains less than `tolerance`.
        """
        def log_variances(noise):
            return np.log(np.r_[noise.pixel_variance, noise.view_sd[moving] ** 2])

        def stepped(woodbury):   # one EM step, its Woodbury factors and -log L
            noise = self._em_step(woodbury, 0)
            woodbury = self._woodbury(noise)
            return noise, woodbury, self.negative_log_likelihood(noise, woodbury)
        moving = noise.view_sd > 0.0   # (a variance at 0 stays there under EM)
        woodbury = self._woodbury(noise)
        value = self.negative_log_likelihood(noise, woodbury)
        for _ in range(NOISE_ITERATIONS // 3):
            first = self._em_step(woodbury, 0)
            second = stepped(self._woodbury(first))
            x0, x1, x2 = (log_variances(n) for n in (noise, first, second[0]))
            r, v = x1 - x0, x2 - 2.0 * x1 + x0
            best = second
            if np.all(np.isfinite(v)) and np.any(v):
                alpha = min(-np.linalg.norm(r) / np.linalg.norm(v), -1.0)
                x = np.clip(x0 - 2.0 * alpha * r + alpha * alpha * v, -700.0, 700.0)
                sd = noise.view_sd.copy()
                sd[moving] = np.exp(0.5 * x[1:])
                extrapolated = ViewNoise(max(float(np.exp(x[0])), VARIANCE_FLOOR), sd)
                candidate = stepped(self._woodbury(extrapolated))
                if candidate[2] <= second[2]:
                    best = candidate
            gain = value - best[2]
            if gain < 0.0:   # (EM never loses likelihood: rounding)
                break
            noise, woodbury, value = best
            if gain < tolerance:
                break
        return noise

    def _em_step(self, woodbury, unknowns_per_variance):
        """Return the ViewNoise of one EM step (fit_noise) from the noise of `woodbury`."""
        d, B_inv, u = woodbury
        posterior = d[:, None] * B_inv * d
        mean = d * np.einsum('vij,vj->vi', B_inv, u)
        view_variance = (np.sum(mean ** 2 + np.einsum('vii->vi', posterior), axis=0)
                         / max(len(mean) - unknowns_per_variance, 1))
        misfit = (self.eWe - 2.0 * np.einsum('vi,vi->v', mean, self.GWe)
                  + np.einsum('vi,vij,vj->v', mean, self.GWG, mean)
                  + np.einsum('vij,vji->v', self.GWG, posterior))
        return ViewNoise(max(float(misfit.sum() / self.count.sum()), VARIANCE_FLOOR),
                         np.sqrt(view_variance))

    def normal_equations(self, noise):
        """Return J^T C^-1 J (P x P, P unknowns) and J^T C^-1 e (P,), summed over the views."""
        A, g = self.view_normal_equations(noise)
        return A.sum(axis=0), g.sum(axis=0)

    def view_normal_equations(self, noise):
        """Return each view's J^T C^-1 J (N, P, P) and J^T C^-1 e (N, P)."""
        d, B_inv, u = self._woodbury(noise)
        U = self.JWG * d / noise.pixel_variance
        A = self.JWJ / noise.pixel_variance - U @ B_inv @ np.swapaxes(U, 1, 2)
        g = self.JWe / noise.pixel_variance - np.einsum('vij,vjk,vk->vi', U, B_inv, u)
        return A, g


def refine_reprojection(link_q, link_t, views, camera, x_q, x_t, o_q, o_t, robust=True,
                        max_iterations=MAX_ITERATIONS, view_errors=None, focal=None):
    """
    Fit X and O to the corners of `views` ([(object_points, image_points)], one per link pose).

    Starts from (x_q, x_t, o_q, o_t), e.g. the pose-based refinement's answer; returns a
    ReprojectionFit: with each view's shared error when the corners show one
    (VIEW_ERROR_EVIDENCE), else on the pixels' noise alone; view_errors True or False
    decides instead. Then with camera_info's focal lengths scaled when the corners show that
    too (FOCAL_EVIDENCE, from MIN_FOCAL_VIEWS views on); focal True or False decides instead.
    """
    link_q, link_t = np.asarray(link_q, dtype=float), np.asarray(link_t, dtype=float)
    corners = Corners.of(views)
    model = (np.asarray(x_q, float), np.asarray(x_t, float), np.asarray(o_q, float),
             np.asarray(o_t, float))
    fit_from = partial(_fit, link_q, link_t, corners, camera)
    chosen, plain_w, spread, held_out = fit_from(model, robust, max_iterations, False)
    evidence, shared = None, False
    if view_errors is not False:
        fitted = fit_from(chosen.model, robust, max_iterations, True)
        evidence = _evidence(link_q, link_t, corners, camera, chosen, fitted[0], plain_w)
        shared = view_errors if view_errors is not None else evidence >= VIEW_ERROR_EVIDENCE
        if shared:
            chosen, _, spread, held_out = fitted
    scale_fitted, focal_evidence = False, None
    if focal or (focal is None and len(views) >= MIN_FOCAL_VIEWS):
        scaled, _, scaled_spread, scaled_held_out = fit_from(chosen.model, robust,
                                                             max_iterations, shared, True)
        focal_evidence = _focal_evidence(link_q, link_t, corners, camera, chosen, scaled,
                                         plain_w, shared)
        if focal or focal_evidence >= FOCAL_EVIDENCE:
            scaled_covariance = scaled_spread()
            variance = (scaled.model_covariance if scaled_covariance is None
                        else scaled_covariance)[12, 12]
            scaled = replace(scaled, focal_scale_sd=float(np.sqrt(variance)))
            scale_fitted = focal or (abs(scaled.focal_scale - 1.0)
                                     >= FOCAL_SIGMAS * scaled.focal_scale_sd)
            if scale_fitted:
                chosen, covariance, held_out = scaled, scaled_covariance, scaled_held_out
    if not scale_fitted:
        covariance = spread()
    return replace(chosen, resampled=None if covariance is None else covariance[:6, :6],
                   held_out=held_out(), view_error_evidence=evidence,
                   focal_evidence=focal_evidence)


def _evidence(link_q, link_t, corners, camera, plain, shared, w):
    """
    Return twice the log-likelihood ratio of the views' errors (VIEW_ERROR_EVIDENCE).

    Both likelihoods with the plain fit's weights w, their noise by maximum likelihood; with
    the views' errors at the best of the two fits' answers and of none (so never below 0).
    """
    at_plain, at_shared = (_likelihood_sums(link_q, link_t, corners, camera, fit, w, True)
                           for fit in (plain, shared))
    none = ViewNoise(max(float(at_plain.eWe.sum() / at_plain.count.sum()), VARIANCE_FLOOR),
                     np.zeros(6))
    start = ViewNoise(shared.pixel_noise_px ** 2,
                      np.maximum(shared.view_error, START_VIEW_ERROR))
    without = at_plain.negative_log_likelihood(none)
    fitted = min(sums.negative_log_likelihood(sums.maximum_likelihood_noise(start))
                 for sums in (at_plain, at_shared))
    return 2.0 * (without - min(without, fitted))


def _focal_evidence(link_q, link_t, corners, camera, fixed, scaled, w, shared):
    """
    Return twice the log-likelihood ratio of fitting the focal scale (FOCAL_EVIDENCE).

    The residuals of the fit with camera_info's focal lengths (`fixed`) and of the one with
    them scaled, under the same noise family (with the views' errors when `shared`), each
    with the weights w and its noise by maximum likelihood; never below 0.
    """
    def likelihood(fit):
        sums = _likelihood_sums(link_q, link_t, corners, camera, fit, w, shared)
        start = ViewNoise(fit.pixel_noise_px ** 2,
                          np.maximum(fit.view_error, START_VIEW_ERROR) if shared
                          else np.zeros(6))
        return sums.negative_log_likelihood(sums.maximum_likelihood_noise(start))
    without, with_scale = likelihood(fixed), likelihood(scaled)
    return 2.0 * max(without - with_scale, 0.0)


def _likelihood_sums(link_q, link_t, corners, camera, fit, w, shared):
    """Return the _ViewSums of the noise's likelihood at `fit` (its focal scale), weights w."""
    seen_by = with_focal_scale(camera, fit.focal_scale)
    predicted, _, G = pixels_and_jacobians(link_q, link_t, corners, seen_by, fit.model, shared)
    return _ViewSums(None, G, corners.pixels - predicted, w, corners.view)


def _fit(link_q, link_t, corners, camera, model, robust, max_iterations, shared, focal=False):
    """
    Return (ReprojectionFit, weights, covariance over the views, HeldOut) from `model`.

    The covariance (all the unknowns') and the HeldOut are functions, called for the chosen
    fit alone (`resampled` and `held_out` None here).
    shared: with the views' errors; else without. focal: with the focal scale as a 13th
    unknown (with_focal_scale), from 1.
    """
    scale = 1.0

    def linearised(model, scale):
        seen_by = with_focal_scale(camera, scale)
        predicted, J, G = pixels_and_jacobians(link_q, link_t, corners, seen_by, model, shared)
        if focal:   # u - c = s (f x'): d u / d s = (u - c) / s
            J = np.concatenate([J, ((predicted - seen_by.K[:2, 2]) / scale)[..., None]],
                               axis=2)
        return corners.pixels - predicted, J, G

    def moved(step, model, scale):
        return apply_step(step[:12], *model), scale + (step[12] if focal else 0.0)
    unknowns = 13 if focal else 12

    noise = ViewNoise(1.0, np.zeros(6))   # (without the views' errors: set by each step)
    if shared:   # the weights and pixel noise then change with the noise fit alone
        e = corners.pixels - predicted_pixels(link_q, link_t, corners, camera, model)
        w, sigma = _weights(e, robust, unknowns)
        noise = ViewNoise(sigma ** 2, np.full(6, START_VIEW_ERROR))
    converged, iterations = False, 0
    for iterations in range(1, max_iterations + 1):
        e, J, G = linearised(model, scale)
        if not shared:
            w, sigma = _weights(e, robust, unknowns)
            noise = ViewNoise(sigma ** 2, noise.view_sd)
        sums = _ViewSums(J, G, e, w, corners.view)
        if shared and iterations <= NOISE_REFITS:   # (then fixed: the steps converge as GN's)
            noise = sums.fit_noise(noise)
            if robust:   # each corner's Huber weight, on its residual less its view's error
                w = _huber(e - np.einsum('kai,ki->ka', G,
                                         sums.view_errors(noise)[corners.view]),
                           np.sqrt(noise.pixel_variance))
                sums = _ViewSums(J, G, e, w, corners.view)
        A, g = sums.normal_equations(noise)
        step = np.linalg.lstsq(A, g, rcond=None)[0]
        model, scale = moved(step, model, scale)
        if float(step @ A @ step) < STEP_TOLERANCE ** 2:
            converged = True
            break
    e, J, G = linearised(model, scale)
    if not shared:
        w, sigma = _weights(e, robust, unknowns)
        noise = ViewNoise(sigma ** 2, noise.view_sd)
    sums = _ViewSums(J, G, e, w, corners.view)
    A, _ = sums.normal_equations(noise)
    A_inv = np.linalg.pinv(A)
    squared = np.sum(e * e, axis=1)
    view_rms = np.sqrt(np.bincount(corners.view, squared) / np.bincount(corners.view))
    within = (e - np.einsum('kai,ki->ka', G, sums.view_errors(noise)[corners.view]) if shared
              else e)
    n_views = len(view_rms)
    spread = (partial(_view_jackknife, sums, noise, n_views) if shared else
              partial(_view_blocks, J, e, w, A_inv / noise.pixel_variance, corners.view,
                      n_views))
    return ReprojectionFit(
        quaternion=quat.canonical(model[0]), translation=model[1], object_quaternion=model[2],
        object_translation=model[3], pixel_noise_px=float(np.sqrt(noise.pixel_variance)),
        rms_px=float(np.sqrt(squared.mean())), model_covariance=A_inv,
        resampled=None, converged=converged, iterations=iterations, view_rms_px=view_rms,
        within_view_rms_px=float(np.sqrt(np.mean(np.sum(within * within, axis=1)))),
        view_error=noise.view_sd, focal_scale=scale), w, spread, partial(
            _held_out, link_q, link_t, corners, camera, model, sums, noise, scale, moved)


def with_focal_scale(camera, scale):
    """Return `camera` with its focal lengths (and skew) times `scale`, its centre kept."""
    if scale == 1.0:
        return camera
    K = camera.K.copy()
    K[:2, :2] *= scale
    return replace(camera, K=K)


def _held_out(link_q, link_t, corners, camera, model, sums, noise, scale, moved):
    """
    Return the HeldOut of the fit (`model`, focal `scale`) with the _ViewSums and noise at it.

    The fit without view k is one Gauss-Newton step from the answer with the other views'
    normal equations (the noise kept), as refine's leave-one-out: exact for a linear model,
    and within a small fraction of the uncertainty this close to the optimum.
    """
    A, g = sums.view_normal_equations(noise)
    others, rhs = A.sum(axis=0) - A, (g.sum(axis=0) - g)[..., None]
    try:
        steps = np.linalg.solve(others, rhs)[..., 0]
    except np.linalg.LinAlgError:   # a view the others cannot do without
        steps = (np.linalg.pinv(others) @ rhs)[..., 0]
    n = len(steps)
    quaternions, translations, rms = np.empty((n, 4)), np.empty((n, 3)), np.empty(n)
    for k, step in enumerate(steps):
        without, focal = moved(step, model, scale)
        x_q, x_t, o_q, o_t = without
        R_S, t_S = board_in_camera(link_q[k:k + 1], link_t[k:k + 1], without)
        quaternions[k] = quat.multiply(quat.multiply(quat.conjugate(x_q),
                                                     quat.conjugate(link_q[k])), o_q)
        translations[k] = t_S[0]
        rows = corners.view == k
        e = corners.pixels[rows] - with_focal_scale(camera, focal).project(
            corners.points[rows] @ R_S[0].T + t_S[0])
        rms[k] = np.sqrt(np.mean(np.sum(e * e, axis=1)))
    return HeldOut(quaternions, translations, rms)


def refine_from_poses(samples, views, camera, result, setup='eye_in_hand', robust=True,
                      view_errors=None, focal=None):
    """
    Return the ReprojectionFit started from a pose-based CalibrationResult of `samples`.

    views: [(object_points, image_points)] of each sample's image; the samples the result
    used (sample_ok) are fitted, from its mounting and the mean object pose it implies.
    view_errors, focal: as refine_reprojection's. Its leave_one_out: each view's board pose
    from its corners alone (PnP, with the fit's focal scale) against the fit without that
    view's prediction (HeldOut.errors), as the pose-based validation measures its estimate.
    """
    rotations = SampleRotations.from_samples(samples, setup)
    positions = SamplePositions.from_samples(samples, rotations)
    used = np.asarray(result.sample_ok, dtype=bool)
    link_q, link_t = rotations.link[used], positions.link[used]
    sensor_q, sensor_t = rotations.sensor[used], positions.sensor[used]
    o_q, o_t = object_pose(link_q, link_t, sensor_q, sensor_t, result.quaternion,
                           result.translation)
    fitted = [v for v, ok in zip(views, used) if ok]
    fit = refine_reprojection(link_q, link_t, fitted, camera, result.quaternion,
                              result.translation, o_q, o_t, robust=robust,
                              view_errors=view_errors, focal=focal)
    # Each view's board pose from its corners alone, with the fit's camera (its focal scale).
    seen_by = with_focal_scale(camera, fit.focal_scale)
    for k, (points, pixels) in enumerate(fitted):
        pose = board_pose(np.asarray(points, float), np.asarray(pixels, float), seen_by)
        if pose is not None:   # (else the sample's: a view refused no pose before)
            sensor_q[k], sensor_t[k] = pose.quaternion, pose.position
    return replace(fit, leave_one_out=fit.held_out.errors(sensor_q, sensor_t))


# E[min(r^2, c^2)] / 2 for a 2-D Gaussian residual of unit sigma per axis (r^2 ~ chi2 with 2
# degrees of freedom, an exponential of mean 2): Huber's proposal 2 divides by it.
HUBER_SCALE_FACTOR = 1.0 - np.exp(-0.5 * HUBER_SIGMAS ** 2)
SCALE_ITERATIONS = 10


def _huber(e, sigma):
    """Return each corner's Huber weight for its residual (K, 2) at pixel noise sigma."""
    r = np.linalg.norm(e, axis=1)
    return np.minimum(1.0, HUBER_SIGMAS * sigma / np.maximum(r, 1e-12))


def _weights(e, robust, unknowns):
    """Return each corner's Huber weight and the pixel noise sigma (per axis)."""
    r = np.linalg.norm(e, axis=1)
    dof = max(e.size - unknowns, 1)
    if not robust:
        return np.ones(len(r)), max(float(np.sqrt(np.sum(r * r) / dof)), 1e-6)
    sigma = max(float(np.median(r)) / 1.1774, 1e-6)   # the median of a 2-D Gaussian's norm
    for _ in range(SCALE_ITERATIONS):   # proposal 2: sigma^2 = sum min(r, c sigma)^2 / (b dof)
        clipped = np.minimum(r, HUBER_SIGMAS * sigma)
        sigma = max(float(np.sqrt(np.sum(clipped * clipped) / (HUBER_SCALE_FACTOR * dof))),
                    1e-6)
    return _huber(e, sigma), sigma


def _view_jackknife(sums, noise, n_views):
    """
    Return the unknowns' covariance over blocks of views left out in turn (None: too few views).

    Without each block the noise (the views' shared errors above all) is fitted again to the
    other views, and one Gauss-Newton step from the answer gives that replicate's mounting:
    the spread includes the noise model's own estimation from a few views, which the
    sandwich cannot see (module docstring).
    """
    if n_views < MIN_BLOCK_VIEWS:
        return None
    moves = []
    for block in np.array_split(np.arange(n_views), min(VIEW_BLOCKS, n_views)):
        keep = np.ones(n_views, bool)
        keep[block] = False
        part = sums.of_views(keep)
        A, g = part.normal_equations(part.fit_noise(noise))
        moves.append(np.linalg.lstsq(A, g, rcond=None)[0])
    moves = np.array(moves)
    centred = moves - moves.mean(axis=0)
    count = len(moves)
    return (count - 1) / count * centred.T @ centred


def _view_blocks(J, e, w, A_inv, view, n_views):
    """
    Return the unknowns' covariance over blocks of views (module docstring; None: too few views).

    A^-1 (sum_b s_b s_b^T) A^-1 with s_b = J_b^T W_b^1/2 (I - H_bb)^-1/2 W_b^1/2 e_b, the
    block's whitened residuals corrected by the root of I - H_bb (symmetric, by eigenvalues);
    A_inv: the (pseudo-)inverse of the weighted normal matrix of J, e, w.
    """
    if n_views < MIN_BLOCK_VIEWS:
        return None
    unknowns = J.shape[2]
    scatter = np.zeros((unknowns, unknowns))
    for block in np.array_split(np.arange(n_views), min(VIEW_BLOCKS, n_views)):
        rows = np.isin(view, block)
        root_w = np.sqrt(np.repeat(w[rows], 2))
        J_b = J[rows].reshape(-1, unknowns) * root_w[:, None]
        e_b = e[rows].reshape(-1) * root_w
        values, vectors = np.linalg.eigh(np.eye(len(e_b)) - J_b @ A_inv @ J_b.T)
        corrected = vectors @ ((vectors.T @ e_b) / np.sqrt(np.maximum(values, 1e-6)))
        score = J_b.T @ corrected
        scatter += np.outer(score, score)
    return A_inv @ scatter @ A_inv


def cramer_rao_covariance(link_q, link_t, views, camera, model, sigma_px):
    """Return the 12 x 12 bound sigma^2 (J^T J)^-1 at the true model, pixel noise sigma_px."""
    corners = Corners.of(views)
    J = jacobian(np.asarray(link_q, float), np.asarray(link_t, float), corners, camera,
                 tuple(np.asarray(m, float) for m in model)).reshape(-1, 12)
    return sigma_px ** 2 * np.linalg.inv(J.T @ J)
