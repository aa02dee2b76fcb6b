"""
Robots that cannot turn the link freely: SCARA-like arms (one rotation axis) and gantries (none).

When every motion turns the link about one axis a, the paper's rotation equation (its Case 1)
leaves the rotation about a free. The translations still fix it: with the object fixed,
o = l_i + R_Li (t_X + R_X s_i) for every sample (refine.py's model, links inverted for
eye-to-hand), and the s_i seen from different positions pin R_X down. What no motion can show
is the offset along a: R_Li a is the same for every i, so t_X + lambda a with o + lambda R_L0 a
fits exactly as well. A gantry (no rotation) leaves the whole of t_X so: with R_Li constant,
t_X and o trade freely; its rotation comes from the translations alone, an orthogonal
Procrustes (Kabsch) fit of the sensor's displacements to the link's.

`fit` finds X and O by Gauss-Newton on refine.py's residuals over the determined directions
only (the steps keep t_X fixed along the undetermined directions, which removes the null
vectors [0, a, 0, R_L0 a], or [0, e_k, 0, R_L0 e_k] for a gantry), starting from the best
rotation about a on a grid (single axis) or from Kabsch (none), with the translations solved
linearly for each candidate and t_X's part along the undetermined directions held at `known`'s
(the user's prior; zero when none is given) from the start. The uncertainty is the sandwich
covariance over the determined directions: zero along the undetermined ones, which
the result names instead (its scatter from leave-one-out residuals, HC3: cautious rather than
over-confident with few samples). Noise: one level for rotation, one for translation, from the
residuals (plain least squares: no outlier rejection on this path).
"""

from dataclasses import dataclass

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.refine import apply_step, jacobian, lever, residuals
from quatcal_ros.core.solver import DegenerateMotionError

# Motions whose rotation axes lie within this of one line turn about a single axis.
SINGLE_AXIS_DEG = 2.0
# A link that never turns by this much (nor by min_motion_deg) never turns: a gantry. Not
# min_motion_deg alone, which says which motions count: set above an arm's largest turn it
# made the arm a gantry, with its translation set to zero.
NEVER_TURNS_DEG = 5.0
GRID_STEPS = 72
MAX_ITERATIONS = 30
STEP_TOLERANCE = 1e-10       # squared step length in units of its sigmas
MIN_NOISE = np.array([1e-6] * 3 + [1e-6] * 3)
MAX_CONDITION = 1e12         # of the normal matrix over the determined directions
# How the error begins when those directions are not determined either.
NOT_EITHER = 'the translations do not fix the rotation either: '
# A sample the fit cannot do without has leverage 1: within this of it (rounding). Measured
# on SCARA and gantry cells: 1e-12 where three samples leave no spare equation without one;
# 3e-5 and more elsewhere, where the leave-one-out uncertainty is cautious (error / reported
# RMS 0.35 up to 1e-3, 4 samples, 600 cells) rather than rounding.
ESSENTIAL_LEVERAGE = 1e-6


class EssentialSampleError(DegenerateMotionError):
    """The data fix the mounting only with every sample: no uncertainty can be had."""


@dataclass(frozen=True)
class ReducedMotion:
    """How the link turns: kind 'single_axis' about `axis` (link frame, unit) or 'none'."""

    kind: str
    axis: np.ndarray = None


def reduced_motion(rotations, min_motion_deg):
    """Return the ReducedMotion of motions.SampleRotations, or None (the link turns freely)."""
    turned = quat.rotation_vector(quat.multiply(quat.conjugate(rotations.link[:1]),
                                                rotations.link))
    angles = np.linalg.norm(turned, axis=1)
    least = np.radians(min(min_motion_deg, NEVER_TURNS_DEG))
    if angles.max() < least:
        return ReducedMotion('none')
    moved = turned[angles > 0.5 * least]
    _, spread, axes = np.linalg.svd(moved, full_matrices=False)
    if len(spread) > 1 and spread[1] > np.sin(np.radians(SINGLE_AXIS_DEG)) * spread[0]:
        return None
    axis = axes[0] / np.linalg.norm(axes[0])
    axis = np.where(np.abs(axis) < 1e-12, 0.0, axis)   # no -0.0 or 3e-16 in the output
    return ReducedMotion('single_axis', axis * np.sign(axis[np.argmax(np.abs(axis))]) + 0.0)


@dataclass(frozen=True)
class ReducedFit:
    """X and O over the determined directions, their covariance, what stays undetermined."""

    x_q: np.ndarray
    x_t: np.ndarray
    o_q: np.ndarray
    o_t: np.ndarray
    start_q: np.ndarray          # the closed form: the grid's (or Kabsch's) rotation
    start_t: np.ndarray
    covariance: np.ndarray       # 12 x 12 sandwich, zero along the undetermined directions
    model_covariance: np.ndarray
    noise: np.ndarray            # (6,) per-axis noise: rotation (rad), translation (m)
    rotation_residuals: np.ndarray   # (N, 3) rad
    leave_one_out: np.ndarray    # (N, 6) predicted residuals, rad and m
    undetermined: np.ndarray     # (k, 3) unit directions of t_X the data do not fix
    converged: bool


def fit(rotations, positions, motion, known=None):
    """Return the ReducedFit of SampleRotations / SamplePositions (module docstring)."""
    link_q, link_t = rotations.link, positions.link
    sensor_q, sensor_t = rotations.sensor, positions.sensor
    R_L = rotations.link_matrices
    undetermined = (np.eye(3) if motion.kind == 'none' else motion.axis[None])
    # The gauge: t_X does not move along the undetermined directions (O takes up the rest).
    fixed = np.array([np.concatenate([np.zeros(3), d, np.zeros(6)]) for d in undetermined]).T
    basis = _complement(fixed)
    # The gauge holds t_X along the undetermined directions where it starts: at the prior.
    anchor = (np.zeros(3) if known is None
              else undetermined.T @ (undetermined @ np.asarray(known, dtype=float)))
    x_q = (_kabsch_rotation(R_L, link_t, sensor_t) if motion.kind == 'none'
           else _grid_rotation(rotations, positions, motion.axis, anchor))
    x_t, o_t = _translations(R_L, link_t, sensor_t, x_q, undetermined, anchor)
    o_q = quat.average(quat.multiply(quat.multiply(link_q, x_q), sensor_q))
    start = (x_q, x_t)
    n = len(link_q)
    converged = False
    for _ in range(MAX_ITERATIONS):
        e, J, noise = _linearised(link_q, link_t, sensor_q, sensor_t, R_L, x_q, x_t, o_q, o_t,
                                  basis, n)
        A = np.einsum('nai,naj->ij', J, J)
        g = np.einsum('nai,na->i', J, e)
        if np.linalg.cond(A) > MAX_CONDITION:
            raise DegenerateMotionError(
                NOT_EITHER + 'move the link to positions spread in at least two directions '
                '(and, for a single rotation axis, turn it by different angles)')
        step = -np.linalg.solve(A, g)
        x_q, x_t, o_q, o_t = apply_step(basis @ step, x_q, x_t, o_q, o_t)
        if step @ A @ step < STEP_TOLERANCE:
            converged = True
            break
    e, J, noise = _linearised(link_q, link_t, sensor_q, sensor_t, R_L, x_q, x_t, o_q, o_t,
                              basis, n)
    A = np.einsum('nai,naj->ij', J, J)
    A_inv = np.linalg.inv(A)
    scores = np.einsum('nai,na->ni', J, e)
    # The sandwich's scatter from each sample's residual predicted without it (HC3). HC2 was
    # over-confident with few samples here (error / uncertainty RMS 1.7 at 4 samples, 40
    # cells); HC3 errs on the cautious side there (0.45-0.9) and is 0.8-1.1 from 10 samples.
    left_out = _leave_one_out(A, J, e, scores)
    held = np.einsum('nai,na->ni', J, left_out)
    scatter = np.einsum('ni,nj->ij', held, held)
    covariance = basis @ (A_inv @ scatter @ A_inv) @ basis.T   # rad and m: J is whitened
    model = basis @ A_inv @ basis.T
    rotation, _ = residuals(link_q, link_t, sensor_q, sensor_t, x_q, x_t, o_q, o_t, R_L)
    return ReducedFit(x_q, x_t, o_q, o_t, *start, covariance, model, noise, rotation,
                      left_out * noise, undetermined, converged)


def _complement(fixed):
    """Return an orthonormal basis (12, 12 - k) of the directions orthogonal to `fixed`."""
    q, _ = np.linalg.qr(fixed, mode='complete')
    return q[:, fixed.shape[1]:]


def _linearised(link_q, link_t, sensor_q, sensor_t, R_L, x_q, x_t, o_q, o_t, basis, n):
    """Return the whitened residuals (N, 6), Jacobian (N, 6, m) over `basis`, noise (6,)."""
    rotation, position = residuals(link_q, link_t, sensor_q, sensor_t, x_q, x_t, o_q, o_t, R_L)
    dof = max(6 * n - basis.shape[1], 1) / (6.0 * n)
    sigma_r = max(np.sqrt(np.mean(rotation ** 2) / dof), MIN_NOISE[0])
    sigma_t = max(np.sqrt(np.mean(position ** 2) / dof), MIN_NOISE[3])
    noise = np.array([sigma_r] * 3 + [sigma_t] * 3)
    J = jacobian(R_L, quat.matrix_from_quaternion(x_q), lever(link_q, link_t, x_t, o_t, R_L))
    e = np.concatenate([rotation, position], axis=1) / noise
    return e, (J / noise[None, :, None]) @ basis, noise


def _translations(R_L, link_t, sensor_t, x_q, undetermined, anchor):
    """
    Return (t_X, t_O) that fit o = l_i + R_Li (t_X + R_X s_i) best for rotation x_q.

    t_X's part along the undetermined directions (k, 3) held at `anchor`'s (fit's gauge: the
    prior known_translation, else zero): there the data trade t_X for t_O exactly only when
    the link turns exactly about one axis (or not at all); with the few microradians of
    wobble a real link has, a least-squares (even minimum-norm) solution over all six would
    put kilometres there, fitting the wobble. Held at zero instead of a given prior, a link
    that turns a degree or two there left a misfit of |t_X| times that turn (eye_to_hand,
    t_X about 1 m: the rotation error 1.6 deg instead of 0.2).
    """
    R_X = quat.matrix_from_quaternion(x_q)
    n = len(R_L)
    free = np.linalg.qr(undetermined.T, mode='complete')[0][:, len(undetermined):]   # (3, m)
    A = np.concatenate([-R_L @ free, np.repeat(np.eye(3)[None], n, axis=0)], axis=2)
    rhs = (link_t + np.einsum('nij,nj->ni', R_L, anchor + sensor_t @ R_X.T)).ravel()
    solution = np.linalg.lstsq(A.reshape(3 * n, -1), rhs, rcond=None)[0]
    m = free.shape[1]
    return anchor + free @ solution[:m], solution[m:]


def _position_cost(R_L, link_t, sensor_t, x_q, undetermined, anchor):
    x_t, o_t = _translations(R_L, link_t, sensor_t, x_q, undetermined, anchor)
    R_X = quat.matrix_from_quaternion(x_q)
    predicted = link_t + np.einsum('nij,nj->ni', R_L, x_t + sensor_t @ R_X.T)
    return float(np.sum((predicted - o_t) ** 2))


def _grid_rotation(rotations, positions, axis, anchor):
    """Return the rotation mapping the sensor's motion axis to `axis`, best turned about it."""
    link_turns = quat.rotation_vector(quat.multiply(quat.conjugate(rotations.link[:1]),
                                                    rotations.link))
    sensor_turns = quat.rotation_vector(quat.multiply(rotations.sensor[:1],
                                                      quat.conjugate(rotations.sensor)))
    signs = np.sign(link_turns @ axis)
    b = (signs[:, None] * sensor_turns).sum(axis=0)
    b /= np.linalg.norm(b)
    base = _rotation_between(b, axis)
    R_L, link_t, sensor_t = rotations.link_matrices, positions.link, positions.sensor
    candidates = [quat.multiply(quat.from_axis_angle(axis, phi), base)
                  for phi in np.linspace(0.0, 2 * np.pi, GRID_STEPS, endpoint=False)]
    costs = [_position_cost(R_L, link_t, sensor_t, q, axis[None], anchor) for q in candidates]
    return candidates[int(np.argmin(costs))]


def _rotation_between(b, a):
    """Return the quaternion of the smallest rotation taking unit b to unit a."""
    cross, dot = np.cross(b, a), float(np.dot(b, a))
    if dot < -1.0 + 1e-12:   # opposite: half a turn about any perpendicular axis
        perpendicular = np.cross(b, [1.0, 0.0, 0.0])
        if np.linalg.norm(perpendicular) < 1e-6:
            perpendicular = np.cross(b, [0.0, 1.0, 0.0])
        return quat.from_axis_angle(perpendicular, np.pi)
    return quat.normalize(np.concatenate([[1.0 + dot], cross]))


def _kabsch_rotation(R_L, link_t, sensor_t):
    """Return R_X of a link that never turns: R_X (s_i - s) = -R_L0^T (l_i - l) (Kabsch)."""
    p = sensor_t - sensor_t.mean(axis=0)
    q = -(link_t - link_t.mean(axis=0)) @ R_L[0]
    U, spread, Vt = np.linalg.svd(p.T @ q)
    if spread[1] < 1e-6 * max(spread[0], 1e-300):
        raise DegenerateMotionError(
            'the link never turns and moves along one line only: the rotation about that line '
            'is undetermined; move it in at least two directions')
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return quat.quaternion_from_matrix(Vt.T @ np.diag([1.0, 1.0, d]) @ U.T)


def _leave_one_out(A, J, e, scores):
    """
    Return each sample's residual predicted without it (one Gauss-Newton step), whitened.

    Raises EssentialSampleError when the others cannot do without some sample (its leverage,
    the largest eigenvalue of J_i A^-1 J_i^T, is 1 to rounding: three samples, say): then no
    sample's prediction, and so no uncertainty, can be had from the data.
    """
    leverage = np.linalg.eigvalsh(J @ np.linalg.solve(A, np.swapaxes(J, 1, 2)))[:, -1]
    if leverage.max() > 1.0 - ESSENTIAL_LEVERAGE:
        raise EssentialSampleError(
            f'with {len(e)} samples the fit needs every one of them (without sample '
            f'{int(np.argmax(leverage))} the others do not fix the mounting), so its '
            'uncertainty cannot be estimated: take more samples at new positions')
    predicted = np.empty_like(e)
    for i in range(len(e)):
        without = A - J[i].T @ J[i]
        try:
            moved = np.linalg.solve(without, scores[i])
        except np.linalg.LinAlgError:
            moved = np.linalg.pinv(without) @ scores[i]
        predicted[i] = e[i] + J[i] @ moved
    return predicted
