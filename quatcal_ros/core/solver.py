"""
The two-motion method of Chou and Kamel (1988), Sections 4 and 5, as the paper gives it.

Solves A_a A_z = A_z A_b (eq. (37)) for the rotation A_z from two motions (A_a1, A_b1),
(A_a2, A_b2).  A_z maps sensor coordinates to link coordinates (the rotation of the transform
link -> sensor).  Quaternions are scalar first, (w, x, y, z).  The numbered corrections of
../shared/paper/ERRATA.md are cited as "erratum N".

Steps (the paper's, with the errata):
1. p_a, p_b of each motion; the sign rule a0 * b0 >= 0 (erratum 3); the rotation angles must
   agree (Lemma 4 of Shiu and Ahmad) and must not be zero (eq. (43) divides by sin(theta/2)).
2. B of eq. (45) from the unit axes; its null space V (4x2) in closed form (erratum 5).
3. W = V1^T V2 (eq. (63)), alpha, beta, gamma (eq. (65)-(67)), Case 1/2/3 (Section 5).
4. Newton-Raphson on E(y) = 0 (eq. (68)) with the dimension-reduced step (eq. (70)-(74));
   p_z = V1 y1 (eq. (59)); A_z by eq. (20).
"""

from dataclasses import dataclass

import numpy as np

from quatcal_ros.core import quaternion as quat

# The paper's arbitrary initial guess of Section 6.
PAPER_INITIAL_GUESS = np.array([0.1, 0.2, 0.1, 0.2])


class DegenerateMotionError(ValueError):
    """The motions cannot determine A_z uniquely; the message says why and what would help."""


class NoRotationError(DegenerateMotionError):
    """A motion rotates (almost) not at all: its axis, and so eq. (43), is undefined."""


class AngleMismatchError(DegenerateMotionError):
    """theta_a != theta_b: A_a and A_b are not similar matrices, so the data are inconsistent."""


class ParallelAxesError(DegenerateMotionError):
    """Case 1: the two motion axes are parallel or anti-parallel."""


@dataclass(frozen=True)
class TwoMotionSolution:
    """Everything the paper computes on the way to A_z (DESIGN.md contract 1)."""

    quaternion: np.ndarray   # p_z, (w, x, y, z), unit, w >= 0
    matrix: np.ndarray       # A_z, 3x3, eq. (20)
    V1: np.ndarray           # 4x2 null-space basis of B_1 (eq. (54), (82))
    V2: np.ndarray           # 4x2 null-space basis of B_2 (eq. (83))
    W: np.ndarray            # 2x2, eq. (63)
    alpha: float             # eq. (65)
    beta: float              # eq. (66)
    gamma: float             # eq. (67)
    case: int                # 2 or 3 (Section 5)
    y: np.ndarray            # [y11, y12, y21, y22] at convergence, eq. (49)
    iterations: int          # Newton-Raphson steps taken
    residual: float          # max |E_k| at the end, eq. (68)
    last_correction: float   # max |Delta y_k| of the last step (the paper's "precision")


def motion_axis_angle(A, name='motion'):
    """Return unit quaternion p (w >= 0), unit axis u and angle theta in [0, pi] of A."""
    p = quat.quaternion_from_matrix(A)
    axis, angle = quat.axis_angle(p)
    return p, axis, angle


def null_space_basis(u_a, u_b):
    """
    Orthonormal 4x2 basis of the null space of B in eq. (45), in closed form (erratum 5).

    For c = u_a . u_b >= -0.9 the basis of erratum 5 with the paper's printed signs:
    column 0 is -[1 + c, u_b x u_a] / n, column 1 is +-[0, u_a + u_b] / n with its first
    non-zero vector component positive, n = sqrt(2 (1 + c)).  Near u_b = -u_a that basis loses
    accuracy (n -> 0), and a second closed form is used: with d = u_a - u_b and m = u_a + u_b,
    B [p0, v] = 0 holds exactly when v . d = 0 and p0 = -d . (m x v) / |d|^2, so any two vectors
    t, s perpendicular to d give the basis after Gram-Schmidt.  At u_b = -u_a it reduces to
    {[0, v]: v perpendicular to u_a}, as erratum 5 requires.
    """
    u_a = np.asarray(u_a, dtype=float)
    u_b = np.asarray(u_b, dtype=float)
    c = float(u_a @ u_b)
    if 1.0 + c >= 0.1:
        n = np.sqrt(2.0 * (1.0 + c))
        v1 = np.concatenate([[1.0 + c], np.cross(u_b, u_a)]) / n
        v2 = np.concatenate([[0.0], u_a + u_b]) / n
        first = v2[1:][np.argmax(np.abs(v2[1:]) > 1e-12)]
        return np.column_stack([-v1, v2 if first > 0 else -v2])
    d = u_a - u_b
    m = u_a + u_b
    t = np.cross(d, np.eye(3)[np.argmin(np.abs(d))])
    t /= np.linalg.norm(t)
    s = np.cross(d / np.linalg.norm(d), t)
    d2 = float(d @ d)
    n_t = np.concatenate([[-(d @ np.cross(m, t)) / d2], t])
    n_s = np.concatenate([[-(d @ np.cross(m, s)) / d2], s])
    e1 = n_t / np.linalg.norm(n_t)
    e2 = n_s - (e1 @ n_s) * e1
    return np.column_stack([e1, e2 / np.linalg.norm(e2)])


def _checked_motion(A_a, A_b, index, min_rotation, angle_tolerance):
    """Axes of motion `index` with the sign rule of erratum 3, or a DegenerateMotionError."""
    p_a, u_a, theta_a = motion_axis_angle(A_a)
    p_b, u_b, theta_b = motion_axis_angle(A_b)
    if min(theta_a, theta_b) < min_rotation:
        raise NoRotationError(
            f'motion {index} rotates by only {np.degrees(theta_a):.4g} deg (link) / '
            f'{np.degrees(theta_b):.4g} deg (sensor), under the minimum of '
            f'{np.degrees(min_rotation):.4g} deg: its rotation axis is undefined; '
            'make a motion that rotates the link by at least 10 degrees')
    if abs(theta_a - theta_b) > angle_tolerance:
        raise AngleMismatchError(
            f'motion {index}: the link rotates by {np.degrees(theta_a):.6g} deg but the sensor '
            f'by {np.degrees(theta_b):.6g} deg (tolerance {np.degrees(angle_tolerance):.3g} '
            'deg); A_a and A_b must rotate by the same angle: check that both poses were taken '
            'at the same instants and that the sensor pose is the object in the sensor frame')
    # Erratum 3: p_a and p_b must describe the rotation with scalar parts of the same sign.
    # quaternion_from_matrix returns w >= 0 for both, so the rule holds except at half turns,
    # where w ~ 0 and the sign of u_b relative to u_a is not fixed by the motion itself.
    half_turn = max(abs(p_a[0]), abs(p_b[0])) < 1e-6
    return u_a, u_b, half_turn


def _resolve_half_turn_signs(axes):
    """Fix the sign of u_b of half-turn motions so that u_a1.u_a2 == u_b1.u_b2."""
    (u_a1, u_b1, half1), (u_a2, u_b2, half2) = axes
    if not (half1 or half2):
        return u_b1, u_b2
    if half1 and half2:
        # Negating both u_b still satisfies both motions: A_z and A_z rot(u_b1 x u_b2, pi).
        raise DegenerateMotionError(
            'both motions are half turns (180 deg): two rotations fit them, so A_z is '
            'ambiguous; make a motion of less than 180 degrees')
    c_a = float(u_a1 @ u_a2)
    if abs(c_a) < 1e-6:
        raise DegenerateMotionError(
            'a motion is a half turn (180 deg) and the two motion axes are perpendicular: '
            'the sign of the half-turn axis, and so A_z, is ambiguous; '
            'make motions of less than 180 degrees')
    if np.sign(float(u_b1 @ u_b2)) != np.sign(c_a):
        if half2:
            u_b2 = -u_b2
        else:
            u_b1 = -u_b1
    return u_b1, u_b2


def case_of(alpha, beta, gamma):
    """Section 5: Case 2 when |alpha| or |gamma| is the largest, Case 3 when |beta| is."""
    largest = max(abs(alpha), abs(beta), abs(gamma))
    return 3 if abs(beta) == largest else 2


def residual_vector(y, W, case):
    """E(y1, y2) of eq. (68) for Case 3, and its Case 2 form of erratum 6."""
    y11, y12, y21, y22 = y
    (w11, w12), (w21, w22) = W
    if case == 3:
        e4 = -w12 * y11 - w22 * y12 + y22
    else:
        e4 = -w11 * y11 - w21 * y12 + y21
    return np.array([
        y11 - w11 * y21 - w12 * y22,
        y12 - w21 * y21 - w22 * y22,
        0.5 * (y21 * y21 + y22 * y22 - 1.0),
        e4,
    ])


def newton_correction(y, E, W, alpha, beta, gamma, case):
    """
    Delta y solving J Delta y = E (eq. (69)-(70)) by the closed forms (72)-(74).

    Case 3 row 4 of J is [-w12, -w22, 0, 1]; after eliminating the first two columns it reads
    [0, 0, gamma, beta].  Case 2 (erratum 6) has row 4 = [-w11, -w21, 1, 0], reducing to
    [0, 0, alpha, gamma].  The pivot is the larger of |y21| and |y22|.
    """
    _, _, y21, y22 = y
    (w11, w12), (w21, w22) = W
    E1, E2, E3, E4 = E
    if case == 3:
        c21, c22 = gamma, beta        # reduced row 4: c21 dy21 + c22 dy22 = E4''
        E4r = w12 * E1 + w22 * E2 + E4
    else:
        c21, c22 = alpha, gamma
        E4r = w11 * E1 + w21 * E2 + E4
    if abs(y21) >= abs(y22):
        J_reduced = c22 - (c21 / y21) * y22                  # eq. (72)
        dy22 = (E4r - (c21 / y21) * E3) / J_reduced
        dy21 = (E3 - y22 * dy22) / y21
    else:
        J_reduced = c21 - (c22 / y22) * y21                  # eq. (73)
        dy21 = (E4r - (c22 / y22) * E3) / J_reduced
        dy22 = (E3 - y21 * dy21) / y22
    dy11 = E1 + w11 * dy21 + w12 * dy22                      # eq. (74)
    dy12 = E2 + w21 * dy21 + w22 * dy22
    return np.array([dy11, dy12, dy21, dy22])


def solve_two_motions(Aa1, Ab1, Aa2, Ab2, y0=None, *, min_rotation=np.radians(0.5),
                      angle_tolerance=np.radians(1.0), min_axis_separation=np.radians(0.05),
                      tolerance=1e-13, max_iterations=50):
    """
    Solve A_a A_z = A_z A_b for A_z from two motions by the paper's method.

    Parameters
    ----------
    Aa1 : array_like, 3x3
        Rotation A_a of motion 1, the link's motion, eq. (35).
    Ab1 : array_like, 3x3
        Rotation A_b of motion 1, the sensor's motion, eq. (36).
    Aa2 : array_like, 3x3
        Rotation A_a of motion 2.
    Ab2 : array_like, 3x3
        Rotation A_b of motion 2.
    y0 : array_like, optional
        Initial guess [y11, y12, y21, y22]; default the paper's [0.1, 0.2, 0.1, 0.2].
    min_rotation : float
        Radians; a motion rotating less is refused (NoRotationError).
    angle_tolerance : float
        Radians; |theta_a - theta_b| above it is refused (AngleMismatchError).
    min_axis_separation : float
        Radians; motion axes closer than this to parallel or anti-parallel are Case 1
        (ParallelAxesError).
    tolerance : float
        Newton-Raphson stops when the largest correction max |Delta y_k| <= tolerance.
    max_iterations : int
        Newton-Raphson gives up (DegenerateMotionError) after this many steps.

    Returns
    -------
    TwoMotionSolution; raises a DegenerateMotionError (a ValueError) saying why when the two
    motions cannot determine A_z uniquely.

    """
    motions = [(Aa1, Ab1), (Aa2, Ab2)]
    axes = [_checked_motion(A_a, A_b, k + 1, min_rotation, angle_tolerance)
            for k, (A_a, A_b) in enumerate(motions)]
    u_b1, u_b2 = _resolve_half_turn_signs(axes)
    u_a1, u_a2 = axes[0][0], axes[1][0]
    separation = np.arccos(np.clip(abs(float(u_a1 @ u_a2)), 0.0, 1.0))
    V1 = null_space_basis(u_a1, u_b1)
    V2 = null_space_basis(u_a2, u_b2)
    W = V1.T @ V2                                               # eq. (63)
    (w11, w12), (w21, w22) = W
    alpha = 1.0 - w11 ** 2 - w21 ** 2                           # eq. (65)
    beta = 1.0 - w12 ** 2 - w22 ** 2                            # eq. (66)
    gamma = -w11 * w12 - w21 * w22                              # eq. (67)
    if separation < min_axis_separation or max(abs(alpha), abs(beta), abs(gamma)) < 1e-14:
        raise ParallelAxesError(
            f'Case 1: the two motion axes are {np.degrees(separation):.3g} deg from parallel '
            f'(minimum {np.degrees(min_axis_separation):.3g} deg), so the rotation about that '
            'axis is undetermined; make a motion about an axis at least 30 degrees away '
            f'from link axis [{u_a1[0]:.2f}, {u_a1[1]:.2f}, {u_a1[2]:.2f}]')
    case = case_of(alpha, beta, gamma)
    # Newton-Raphson, y <- y - Delta y (erratum 7), until the correction is below
    # `tolerance`.  The paper's example takes eight steps and its last correction,
    # 2.7e-14, is the printed "precision of 0.27e-13".
    y = np.array(PAPER_INITIAL_GUESS if y0 is None else y0, dtype=float)
    iterations = 0
    correction = np.inf
    while correction > tolerance and iterations < max_iterations:
        E = residual_vector(y, W, case)
        delta = newton_correction(y, E, W, alpha, beta, gamma, case)
        y = y - delta
        iterations += 1
        correction = float(np.max(np.abs(delta)))
        if not np.isfinite(correction):
            break
    residual = float(np.max(np.abs(residual_vector(y, W, case))))
    if not np.all(np.isfinite(y)) or residual > 1e-9:
        raise DegenerateMotionError(
            f'Newton-Raphson did not converge in {max_iterations} steps (max |E| = '
            f'{residual:.3g}); the motions are too close to Case 1: make a motion about a '
            'clearly different axis')
    p_z = quat.canonical(quat.normalize(V1 @ y[:2]))            # eq. (59)
    return TwoMotionSolution(
        quaternion=p_z, matrix=quat.matrix_from_quaternion(p_z), V1=V1, V2=V2, W=W,
        alpha=float(alpha), beta=float(beta), gamma=float(gamma), case=case, y=y,
        iterations=iterations, residual=residual, last_correction=correction)
