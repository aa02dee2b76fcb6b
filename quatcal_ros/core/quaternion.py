"""
Quaternion algebra of Chou and Kamel (1988), Section 2, in numpy.

Every quaternion in this module is an array of shape (..., 4) in **scalar-first** order
(w, x, y, z), the paper's [e0, e1, e2, e3].  ROS messages and the samples CSV use (x, y, z, w):
convert only at those boundaries, with `wxyz_from_xyzw` and `xyzw_from_wxyz`.

Rotation matrices are 3x3 (or (..., 3, 3)) and act on column vectors.  A unit quaternion p
and its matrix A = matrix_from_quaternion(p) satisfy eq. (19)-(20): p (x) [0, v] (x) p* =
[0, A v].
"""

import math

import numpy as np

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def wxyz_from_xyzw(q_xyzw):
    """Reorder (x, y, z, w) (ROS, CSV) to (w, x, y, z) (this package's core)."""
    q = np.asarray(q_xyzw, dtype=float)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


def xyzw_from_wxyz(q_wxyz):
    """Reorder (w, x, y, z) (this package's core) to (x, y, z, w) (ROS, CSV)."""
    q = np.asarray(q_wxyz, dtype=float)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def xyzw_json(q_wxyz):
    """Return the JSON object {"x", "y", "z", "w"} (floats) of a quaternion (w, x, y, z)."""
    return dict(zip('xyzw', (float(v) for v in xyzw_from_wxyz(q_wxyz))))


def xyz_json(v):
    """Return the JSON object {"x", "y", "z"} (floats) of a 3-vector."""
    return dict(zip('xyz', (float(c) for c in v)))


def skew(v):
    """Return the cross-product matrix of eq. (9): its product with b is the cross product."""
    v = np.asarray(v, dtype=float)
    return (v @ _SKEW).reshape(v.shape[:-1] + (3, 3))


# skew(v).ravel() = v @ _SKEW: rows [0, -z, y], [z, 0, -x], [-y, x, 0] of eq. (9).
_SKEW = np.array([[0, 0, 0, 0, 0, -1, 0, 1, 0],
                 [0, 0, 1, 0, 0, 0, -1, 0, 0],
                 [0, -1, 0, 1, 0, 0, 0, 0, 0]], dtype=float)


def multiply(a, b):
    """Hamilton product a (x) b of eq. (6)-(8), (w, x, y, z), broadcasting over leading axes."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim == 1 and b.ndim == 1:   # two quaternions: the same arithmetic on plain floats
        return np.array(_product(*a.tolist(), *b.tolist()))
    if b.ndim == 1:                    # many by one: a (x) b = P-(b) a (eq. (13))
        return a @ minus_matrix(b).T
    return (plus_matrix(a) @ b[..., None])[..., 0]   # a (x) b = P+(a) b


def _product(aw, ax, ay, az, bw, bx, by, bz):
    """Return the components of the Hamilton product (eq. (8)) of a and b, as a list."""
    return [aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw]


def conjugate(q):
    """Conjugate of eq. (3): the vector part negated; the inverse of a unit quaternion."""
    return np.asarray(q, dtype=float) * _CONJUGATE


_CONJUGATE = np.array([1.0, -1.0, -1.0, -1.0])


def plus_matrix(a):
    """
    Return the 'plus' matrix of eq. (11), the left factor of a (x) b = P+(a) b.

    a: (4,) or (..., 4), w first; the result is (4, 4) or (..., 4, 4).
    """
    # Rows [a0, -x, -y, -z], [x, a0, -z, y], [y, z, a0, -x], [z, -y, x, a0].
    return np.asarray(a, dtype=float)[..., _SWAP] * _PLUS_SIGNS


def minus_matrix(b):
    """
    Return the 'minus' matrix of eq. (12), the factor of a (x) b = P-(b) a.

    b: (4,) or (..., 4), w first; the result is (4, 4) or (..., 4, 4).
    """
    # Rows [b0, -x, -y, -z], [x, b0, z, -y], [y, -z, b0, x], [z, y, -x, b0].
    return np.asarray(b, dtype=float)[..., _SWAP] * _MINUS_SIGNS


# The components and signs of the entries of P+ and P- (eqs. (11), (12)).
_SWAP = np.array([[0, 1, 2, 3], [1, 0, 3, 2], [2, 3, 0, 1], [3, 2, 1, 0]])
_PLUS_SIGNS = np.array([[1, -1, -1, -1], [1, 1, -1, 1], [1, 1, 1, -1], [1, -1, 1, 1]], float)
_MINUS_SIGNS = np.array([[1, -1, -1, -1], [1, 1, 1, -1], [1, -1, 1, 1], [1, 1, -1, 1]], float)


def normalize(q):
    """Scale q to unit length; raise ValueError for a zero quaternion."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:   # one quaternion: the same arithmetic on plain floats
        components = q.tolist()
        norm = math.sqrt(sum(c * c for c in components))
        if norm < 1e-12:
            raise ValueError('cannot normalise a zero quaternion')
        return np.array([c / norm for c in components])
    norm = np.sqrt(np.einsum('...i,...i->...', q, q))[..., None]
    if norm.min(initial=1.0) < 1e-12:
        raise ValueError('cannot normalise a zero quaternion')
    return q / norm


def canonical(q):
    """
    Pick the sign of q (which and -q are the same rotation) with w >= 0.

    Ties (w == 0) are broken by the first non-zero vector component being positive, so the
    result is unique for every rotation, 180 degrees included.
    """
    q = np.array(q, dtype=float)
    if q.ndim == 1:   # one quaternion: on plain floats
        for component in q.tolist():
            if abs(component) > 1e-15:
                return -q if component < 0.0 else q
        return q
    w = q[..., :1]
    if np.abs(w).min(initial=1.0) > 1e-15:   # the sign of w decides
        return np.where(w < 0.0, -q, q)
    first = np.argmax(np.abs(q) > 1e-15, axis=-1)[..., None]   # the first non-zero component
    return np.where(np.take_along_axis(q, first, axis=-1) < 0.0, -q, q)


def matrix_from_quaternion(p):
    """
    Rotation matrix of unit quaternion(s) p = (w, x, y, z), eq. (20), (..., 4) -> (..., 3, 3).

    A = (e0^2 - e.e) I + 2 (e e^T + e0 skew(e)); p is normalised first. Every entry is a
    quadratic form of p: for many quaternions, one product of their outer products with the
    constant _MATRIX_OF_OUTER.
    """
    p = normalize(p)
    if p.ndim == 1:   # one quaternion: the same arithmetic on plain floats
        return np.array(_matrix_rows(*p.tolist()))
    outer = (p[..., :, None] * p[..., None, :]).reshape(p.shape[:-1] + (16,))
    return (outer @ _MATRIX_OF_OUTER).reshape(p.shape[:-1] + (3, 3))


def _matrix_rows(w, x, y, z):
    """Return the rows of the rotation matrix (eq. (20)) of the unit quaternion (w, x, y, z)."""
    return [[w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z]]


def _quadratic_form_of_matrix():
    """Return C (16, 9): the entries of eq. (20) are (p p^T).ravel() @ C (C symmetric in a, b)."""
    def entries(p):
        return np.array(_matrix_rows(*p)).ravel()
    e = np.eye(4)
    C = np.zeros((4, 4, 9))
    for a in range(4):
        for b in range(4):
            C[a, b] = (entries(e[a]) if a == b else
                       0.5 * (entries(e[a] + e[b]) - entries(e[a]) - entries(e[b])))
    return C.reshape(16, 9)


_MATRIX_OF_OUTER = _quadratic_form_of_matrix()


def quaternion_from_matrix(A):
    """
    Return the unit quaternion (w, x, y, z), w >= 0, of a 3x3 rotation matrix (eq. (20) inverted).

    Stable for every rotation, 180 degrees included: the symmetric 4x4 matrix K of Bar-Itzhack
    (2000) has the wanted quaternion as the eigenvector of its largest eigenvalue, which also
    gives the nearest rotation when A is slightly non-orthogonal (noisy input).
    """
    A = np.asarray(A, dtype=float)
    if A.shape != (3, 3) or not np.all(np.isfinite(A)):
        raise ValueError('expected a finite 3x3 rotation matrix')
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = A
    K = np.array([
        [m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01],
        [m21 - m12, m00 - m11 - m22, m01 + m10, m02 + m20],
        [m02 - m20, m01 + m10, m11 - m00 - m22, m12 + m21],
        [m10 - m01, m02 + m20, m12 + m21, m22 - m00 - m11],
    ]) / 3.0
    _, vectors = np.linalg.eigh(K)
    return canonical(vectors[:, -1])


def axis_angle(p):
    """
    Return the unit axis u and angle theta in [0, pi] of eq. (16) for a unit quaternion p.

    The axis of a rotation by (almost) zero is undefined; (0, 0, 1) is returned then.
    """
    p = canonical(normalize(p))
    s = np.linalg.norm(p[1:])
    theta = 2.0 * np.arctan2(s, p[0])
    if s < 1e-15:
        return np.array([0.0, 0.0, 1.0]), 0.0
    return p[1:] / s, theta


def from_axis_angle(axis, angle):
    """Return the unit quaternion of a rotation by `angle` (radians) about `axis`, eq. (22)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2.0)], np.sin(angle / 2.0) * axis])


def from_rotation_vector(rotvec):
    """Return the unit quaternion(s) of rotation vector(s) (axis times angle, radians)."""
    rotvec = np.asarray(rotvec, dtype=float)
    if rotvec.ndim == 1:   # one rotation vector: on plain floats
        x, y, z = rotvec.tolist()
        angle = math.sqrt(x * x + y * y + z * z)
        half_sinc = math.sin(0.5 * angle) / angle if angle > 0.0 else 0.5
        return np.array([math.cos(0.5 * angle), half_sinc * x, half_sinc * y, half_sinc * z])
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    # sin(angle/2)/angle, with its limit 1/2 at angle -> 0.
    half_sinc = 0.5 * np.sinc(angle / (2.0 * np.pi))
    return np.concatenate([np.cos(angle / 2.0), half_sinc * rotvec], axis=-1)


def rotation_vector(p):
    """Rotation vector(s) (axis times angle, angle in [0, pi]) of unit quaternion(s) (..., 4)."""
    p = np.asarray(p, dtype=float)
    v = p[..., 1:]
    s = np.sqrt(np.einsum('...i,...i->...', v, v))
    w = p[..., 0]
    # angle / s, signed to put the quaternion on w >= 0 (2 / |w| in the limit s -> 0; v is 0
    # at s == 0 exactly, where any finite scale gives the zero vector)
    scale = np.copysign(2.0 * np.arctan2(s, np.abs(w)) / np.maximum(s, 1e-300), w)
    return scale[..., None] * v


def angle_between(p, q):
    """
    Angle (radians, in [0, pi]) of the rotation taking unit quaternion p to q.

    Computed with atan2 on the relative quaternion p* (x) q: accurate to rounding for tiny
    angles, where arccos(p . q) would resolve only about 1e-8 rad.
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    if p.ndim == 1 and q.ndim == 1:   # two quaternions: the same arithmetic on plain floats
        pw, px, py, pz = p.tolist()
        return _angle(*_product(pw, -px, -py, -pz, *q.tolist()))
    return rotation_angle(multiply(conjugate(p), q))


def rotation_angle(p):
    """Rotation angle (radians, in [0, pi]) of unit quaternion(s) (..., 4)."""
    p = np.asarray(p, dtype=float)
    if p.ndim == 1:   # one quaternion: the same arithmetic on plain floats
        return _angle(*p.tolist())
    return 2.0 * np.arctan2(np.linalg.norm(p[..., 1:], axis=-1), np.abs(p[..., 0]))


def _angle(w, x, y, z):
    """Return rotation_angle of one quaternion given as floats."""
    return 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(w))


def slerp(p, q, fraction):
    """
    Interpolate from p (fraction 0) to q (fraction 1) on the shortest arc (SLERP).

    Broadcasts over leading axes: p, q (..., 4), fraction (...).  Exact for rotation at a
    constant angular velocity; the linear blend is used only where sin(omega) < 1e-9, where
    it agrees with SLERP to rounding.
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    if p.ndim == 1 and q.ndim == 1 and np.ndim(fraction) == 0:   # one pair: on plain floats
        return normalize(np.array(_slerp_blend(p.tolist(), q.tolist(), float(fraction))))
    f = np.asarray(fraction, dtype=float)[..., None]
    dot = np.sum(p * q, axis=-1, keepdims=True)
    q = np.where(dot < 0.0, -q, q)
    omega = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
    sin_omega = np.sin(omega)
    near = sin_omega < 1e-9
    safe = np.where(near, 1.0, sin_omega)
    a = np.where(near, 1.0 - f, np.sin((1.0 - f) * omega) / safe)
    b = np.where(near, f, np.sin(f * omega) / safe)
    return normalize(a * p + b * q)


def _slerp_blend(p, q, f):
    """Return slerp's blend a p + b q (before normalising) of two quaternions as float lists."""
    dot = sum(a * b for a, b in zip(p, q))
    if dot < 0.0:
        q = [-b for b in q]
    omega = math.acos(min(abs(dot), 1.0))
    sin_omega = math.sin(omega)
    if sin_omega < 1e-9:
        a, b = 1.0 - f, f
    else:
        a, b = math.sin((1.0 - f) * omega) / sin_omega, math.sin(f * omega) / sin_omega
    return [a * u + b * v for u, v in zip(p, q)]


def rotate(q, v):
    """Rotate vector(s) v (..., 3) by unit quaternion(s) q (w, x, y, z) (..., 4), eq. (19)."""
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    if q.ndim == 1:   # one rotation: v @ A^T
        return v @ matrix_from_quaternion(q).T
    return (matrix_from_quaternion(q) @ v[..., None])[..., 0]


def average(quaternions, weights=None):
    """
    Average a set of unit quaternions (w, x, y, z) (Markley et al. 2007).

    The eigenvector of the largest eigenvalue of sum w_i q_i q_i^T: insensitive to the sign of
    each q_i, and the maximum-likelihood mean for small scatter. `quaternions` (N, 4), or a
    batch of sets (..., N, 4) averaged each.
    """
    Q = np.asarray(quaternions, dtype=float)
    if Q.ndim < 2:
        Q = Q.reshape(-1, 4)
    weighted = Q if weights is None else Q * np.asarray(weights, dtype=float)[..., None]
    _, vectors = np.linalg.eigh(np.swapaxes(weighted, -1, -2) @ Q)
    return canonical(vectors[..., -1])
