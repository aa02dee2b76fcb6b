"""
How good an estimate is: sample residuals, uncertainty, excitation and the next-motion hint.

The quality figures come from a linear model of the samples.  For the estimate p_z let
Z_i = link_i (x) p_z (x) sensor_i be the object's orientation in the base frame
(motions.SampleRotations.object_orientations); for the true p_z all Z_i are equal.  A small
error delta of p_z, expressed in the frame A_z maps into (the link frame eye-in-hand), rotates
Z_i by R(link_i) delta, so the residual of sample i is
    eps_i = R(link_i) delta - eta + n_i          (rotation vectors, base frame)
with eta the error of the mean object orientation and n_i the sample's own noise, taken
isotropic with variance sigma^2 per axis.  A motion (i, j) sees eps_j - eps_i, so the
least-squares estimate over a motion set K has
    H = sum_k D_k^T D_k,  D_k = R(link_j) - R(link_i),
    cov(delta) = sigma^2 H^-1 (sum_i C_i C_i^T) H^-1,  C_i = sum of +-D_k^T over motions of i,
a sandwich that stays honest when motions share samples (all pairs, consecutive pairs).
D_k^T D_k = 4 sin^2(theta_k / 2) (I - u_k u_k^T): a motion informs every direction except
its own axis u_k, which is why two non-parallel axes are needed (Case 1 of Section 5).
"""

from dataclasses import dataclass
from functools import cached_property
import math

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.numerics import inverse, rms

AXIS_NAMES = ('x', 'y', 'z')


def sample_residuals(rotations, q_z, inliers=None):
    """
    Rotation vectors eps_i (N, 3), radians, base frame, of each Z_i about the mean Z.

    The mean is taken over `inliers` (bool mask or None for all samples).
    """
    return object_residuals(rotations, q_z, inliers)[0]


def object_residuals(rotations, q_z, inliers=None):
    """
    Return sample_residuals and the mean object orientation Z (w, x, y, z) they are about.

    Of each rotation, when q_z holds several (shape (P, 4): residuals (P, N, 3), means (P, 4)).
    """
    Z = rotations.object_orientations(q_z)
    mean = quat.average(Z if inliers is None else Z[..., inliers, :])
    return quat.rotation_vector(quat.multiply(Z, quat.conjugate(mean)[..., None, :])), mean


def noise_sigma(residuals):
    """Per-axis rotation noise (radians) from sample residuals: 3N values, 6 unknowns."""
    dof = 3 * len(residuals) - 6
    if dof <= 0:
        return float('nan')
    centred = residuals - residuals.mean(axis=0)
    return float(np.sqrt(np.sum(centred ** 2) / dof))


def unknown_noise_factor(count):
    """
    Return E[sigma^2 / s^2] for noise_sigma's s of `count` samples: dof / (dof - 2).

    The covariance sigma^2 H^-1 G H^-1 is exact for the true sigma; with s in its place the
    error over the reported uncertainty follows a t with dof = 3 count - 6 degrees of freedom
    (the Bayesian marginal under the usual prior), whose variance is this factor: sqrt(3) in
    the RMS error at 3 samples, 1.22 at 4, 1.04 at 10. inf without a spare degree of freedom.
    So E[(error / reported)^2] = 1 for every result; pooled over many results, the RMS error
    over the RMS reported is then sqrt(1 / factor) (0.58 at 3 samples, 0.82 at 4).
    """
    dof = 3 * count - 6
    return dof / (dof - 2.0) if dof > 2 else math.inf


@dataclass(frozen=True)
class Information:
    """
    The normal matrix H (3x3) of a motion set, the per-sample sums C_i and G = sum C_i C_i^T.

    C_i = sum of D_k^T over the motions ending at sample i minus those starting there; the
    translation's right-hand side and its sensitivity to the rotation are sums over C_i too
    (translation.py), so everything per motion is summed once, here.
    """

    H: np.ndarray
    G: np.ndarray
    C: np.ndarray     # (N, 3, 3)

    @staticmethod
    def of(link_matrices, i, j):
        """H, C and G for motions (i[k], j[k]) given the link rotation matrices (N, 3, 3)."""
        H, C = _motion_sums(link_matrices, i, j)
        return Information(H, _outer_sum(C), C)

    @staticmethod
    def all_pairs(link_matrices, use):
        """
        H, C and G of every pair of the samples `use` (bool mask), in O(N).

        Over all pairs of K samples with R_s = sum R(link_i), H = K^2 I - R_s^T R_s and
        C_n = K R(link_n)^T - R_s^T (zero for samples not used): no motion is formed.
        """
        R = link_matrices[use]
        k = len(R)
        total = R.sum(axis=0)
        C = np.zeros_like(link_matrices)
        C[use] = k * np.transpose(R, (0, 2, 1)) - total.T
        H = k * k * np.eye(3) - total.T @ total
        return Information(H, _outer_sum(C), C)

    def covariance(self, sigma):
        """cov(delta) (3x3, rad^2) for per-axis sample noise sigma (radians)."""
        H_inv = self.H_inverse
        return sigma * sigma * H_inv @ self.G @ H_inv

    @cached_property
    def H_inverse(self):
        """Return H^-1 (its pseudo-inverse when H is singular)."""
        return inverse(self.H)

    def excitation(self):
        """(ratio of weakest to strongest eigenvalue of H in [0, 1], weakest unit axis)."""
        return self._excitation

    @cached_property
    def _excitation(self):
        values, vectors = np.linalg.eigh(self.H)
        if values[-1] <= 0.0:
            axis = np.array([0.0, 0.0, 1.0])
            axis.flags.writeable = False
            return 0.0, axis
        axis = vectors[:, 0]
        axis = axis if axis[np.argmax(np.abs(axis))] > 0 else -axis
        axis.flags.writeable = False   # remembered: callers share it
        return float(max(values[0], 0.0) / values[-1]), axis


def _outer_sum(C):
    """Return sum_n C_n C_n^T of (N, 3, 3) matrices."""
    rows = np.swapaxes(C, 0, 1).reshape(3, -1)
    return rows @ rows.T


def _motion_sums(link_matrices, i, j):
    """Return H = sum_k D_k^T D_k and C (N, 3, 3) of the motions (i[k], j[k])."""
    n = len(link_matrices)
    i, j = np.asarray(i, dtype=int), np.asarray(j, dtype=int)
    D = link_matrices[j] - link_matrices[i]
    H = np.einsum('kji,kjl->il', D, D)
    Dt = np.transpose(D, (0, 2, 1)).reshape(-1, 9)
    C = np.stack([np.bincount(j, Dt[:, e], n) - np.bincount(i, Dt[:, e], n)
                  for e in range(9)], axis=-1).reshape(n, 3, 3)
    return H, C.astype(float, copy=False)   # (bincount of no motions is integer)


def uncertainty_deg(covariance):
    """Return the expected RMS error angle (degrees): sqrt(trace(cov))."""
    return float(np.degrees(rms(covariance)))


def nearest_axis_name(axis, frame='link'):
    """'link z' style name of the coordinate axis closest to `axis` (sign ignored)."""
    return f'{frame} {AXIS_NAMES[int(np.argmax(np.abs(axis)))]}'


def next_motion_hint(ratio, weakest_axis, frame='link', good_ratio=0.2):
    """
    Words for the operator: which motion would improve the estimate most.

    weakest_axis: in `frame`, the frame of the motions' axes ('link' for eye-in-hand, 'base'
    for eye-to-hand); either way it is the link that the robot turns.
    """
    name = nearest_axis_name(weakest_axis, frame)
    others = [f'{frame} {a}' for a in AXIS_NAMES if f'{frame} {a}' != name]
    vector = ', '.join(f'{c:.2f}' for c in weakest_axis)
    if ratio < good_ratio:
        return (f'the rotation about the {name} axis ([{vector}]) is least determined: '
                f'rotate the link about axes perpendicular to it, e.g. tilt about '
                f'{others[0]} or {others[1]}, by 20-40 degrees')
    return ('motions excite all axes; more samples about varied axes reduce the '
            f'uncertainty (weakest: {name})')
