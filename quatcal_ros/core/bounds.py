"""
Cramer-Rao bound of the mounting: the smallest covariance any unbiased estimator can reach.

The model is refine.py's: for sample i, S_i = inv(X) inv(L_i) O, with link poses L_i exact
(inverted for eye-to-hand, as refine gets them) and sensor poses S_i noisy. The noise is
simulation.add_pose_noise's: the measured orientation is exp(r) (x) q with r a rotation
vector of std sigma_r (radians) per axis, and the measured position is p + t with t of std
sigma_t (metres) per axis, all independent Gaussians. The residual refine compares,
log(inv(q_pred) (x) q_meas), is then R^T r, which is again isotropic with std sigma_r per axis;
so the whitened Jacobian of refine, evaluated at the true X and O with the true sigmas, gives
the Fisher information J^T J, and its inverse is the bound. The 12 parameters are ordered as
in refine.whitened_jacobian: X's rotation (left perturbation, radians), X's translation
(metres), O's rotation, O's translation. O is a nuisance parameter the estimator must fit too.
"""

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import inverse_perturbation
from quatcal_ros.core.refine import jacobian, lever, uncertainties, whitened_jacobian


def cramer_rao_covariance(link_q, link_t, x_q, x_t, o_q, o_t, sigma_r, sigma_t):
    """
    Return the 12 x 12 Cramer-Rao covariance (J^T J)^-1 at the true mounting and object pose.

    link_q (N, 4), link_t (N, 3): the link poses as refine gets them (T_base_link for
    eye-in-hand, inverted for eye-to-hand). x_q, x_t: the true mounting X; o_q, o_t: the true
    object pose O (T_base_obj for eye-in-hand, T_link_obj for eye-to-hand). sigma_r: the
    sensor orientation noise, radians per axis of the rotation vector; sigma_t: the sensor
    position noise, metres per axis.
    """
    J = whitened_jacobian(np.asarray(link_q, dtype=float), np.asarray(link_t, dtype=float),
                          np.asarray(x_q, dtype=float), np.asarray(x_t, dtype=float),
                          np.asarray(o_q, dtype=float), np.asarray(o_t, dtype=float),
                          sigma_r, sigma_t)
    return np.linalg.inv(J.T @ J)


def cramer_rao_covariance_general(link_q, link_t, x_q, x_t, o_q, o_t, noise_covariance):
    """
    Return the bound (12 x 12) for sensor noise with any 6x6 covariance in the sensor frame.

    noise_covariance: of (rotation vector of R_meas R_true^T, t_meas - t_true), radians and
    metres: one 6x6 for every sample (simulation.add_sensor_noise draws it), or one per
    sample (N, 6, 6), e.g. with link_noise_covariances() added. The Fisher information is
    sum_i J_i^T Sigma_i^-1 J_i with refine.jacobian's J_i.
    """
    link_q = np.asarray(link_q, dtype=float)
    link_R = quat.matrix_from_quaternion(link_q)
    levers = lever(link_q, np.asarray(link_t, dtype=float), np.asarray(x_t, dtype=float),
                   np.asarray(o_t, dtype=float), link_R)
    J = jacobian(link_R, quat.matrix_from_quaternion(np.asarray(x_q, dtype=float)), levers)
    information = np.broadcast_to(np.linalg.inv(noise_covariance), (len(J), 6, 6))
    return np.linalg.inv(np.einsum('nai,nab,nbj->ij', J, information, J))


def link_noise_covariances(link_q, link_t, x_q, o_t, link_covariance, setup='eye_in_hand'):
    """
    Return (N, 6, 6): the robot-side noise as it shows in each sample's sensor-frame residual.

    The link poses T_base_link are measured as exp(r) R_L, t_L + t (simulation.add_pose_noise's
    model), (r, t) ~ N(0, link_covariance). link_q, link_t are as refine gets them (T_base_link
    for eye-in-hand, inverted for eye-to-hand), x_q the mounting's rotation, o_t the object's
    position. To first order, the predicted sensor pose inv(X) inv(L) O then moves by
        rotation:     -M r',   translation: M [t_O - t_L]x r' - M t',   M = R_X^T R_L^T,
    where (r', t') is the noise of the pose refine uses: (r, t) for eye-in-hand; for the
    inverted pose R = R_L^T of eye-to-hand, r' = -R r and t' = -R t - R [t_base_link]x r.
    Added to the sensor's own covariance, this gives the bound with robot-side noise
    (cramer_rao_covariance_general); tests compare it with finite differences.
    """
    link_q = np.asarray(link_q, dtype=float)
    link_t = np.asarray(link_t, dtype=float)
    R_L = quat.matrix_from_quaternion(link_q)
    n = len(R_L)
    to_refine = np.broadcast_to(np.eye(6), (n, 6, 6))
    if setup == 'eye_to_hand':   # noise of T_base_link, seen on its inverse R_L, t_L
        base_t = -np.einsum('nji,nj->ni', R_L, link_t)   # T_base_link's position
        to_refine = inverse_perturbation(np.transpose(R_L, (0, 2, 1)), base_t)
    R_X = quat.matrix_from_quaternion(np.asarray(x_q, dtype=float))
    M = R_X.T @ np.transpose(R_L, (0, 2, 1))
    to_residual = np.zeros((n, 6, 6))
    to_residual[:, 0:3, 0:3] = -M
    to_residual[:, 3:6, 0:3] = M @ quat.skew(np.asarray(o_t, dtype=float) - link_t)
    to_residual[:, 3:6, 3:6] = -M
    A = to_residual @ to_refine
    return A @ link_covariance @ np.transpose(A, (0, 2, 1))


def rotation_rms_deg(covariance):
    """Return the bound's RMS error angle of X's rotation, degrees: sqrt(trace) of its block."""
    return uncertainties(covariance)[0]


def translation_rms_mm(covariance):
    """Return the bound's RMS error of X's translation, millimetres (Euclidean norm)."""
    return uncertainties(covariance)[1]
