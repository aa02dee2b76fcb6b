"""
Least squares over many motions: the stacked system of eq. (41), solved incrementally.

Each motion k gives B_k p_z = 0 with B_k = P+(p_ak) - P-(p_bk) (eq. (39)-(41), erratum 2),
where p_bk takes the sign that makes it describe the same rotation as p_ak (erratum 3).
Unlike eq. (45) this full-quaternion form never divides by sin(theta/2), so small and
half-turn motions need no special case: they enter with weight ~ sin^2(theta/2).
With noise, p_z minimises sum_k |B_k p_z|^2 subject to |p_z| = 1: the eigenvector of the
smallest eigenvalue of M = sum_k B_k^T B_k.  Adding a motion adds one 4x4 block: O(1).

For samples paired 'all' ways this is the maximum-likelihood estimate under isotropic
rotation noise on each sample: |B_ij p| = |Z_j - Z_i| with Z_i the object orientation in
the base frame (motions.SampleRotations.object_orientations), and the sum over all pairs
of |Z_j - Z_i|^2 is N times the scatter of the Z_i about their mean.
"""

import numpy as np

from quatcal_ros.core import quaternion as quat


def aligned_b(q_a, q_b, reference=None):
    """
    q_b with the sign of erratum 3: a0 * b0 >= 0.

    Near half turns (a0 ~ b0 ~ 0) that rule is decided by noise; given a `reference`
    estimate of p_z, the sign that makes p_a (x) p_z closest to p_z (x) p_b is used instead.
    """
    q_a = np.asarray(q_a, dtype=float).reshape(-1, 4)
    q_b = np.asarray(q_b, dtype=float).reshape(-1, 4)
    if reference is None:
        sign = np.where(q_a[:, 0] * q_b[:, 0] < 0.0, -1.0, 1.0)
    else:
        left = quat.multiply(q_a, reference)
        right = quat.multiply(reference, q_b)
        sign = np.where(np.sum(left * right, axis=1) < 0.0, -1.0, 1.0)
    return q_b * sign[:, None]


def b_matrices(q_a, q_b, reference=None):
    """B_k = P+(p_ak) - P-(p_bk) of eq. (41) for each motion, (K, 4, 4)."""
    q_a = np.asarray(q_a, dtype=float).reshape(-1, 4)
    return quat.plus_matrix(q_a) - quat.minus_matrix(aligned_b(q_a, q_b, reference))


# P+(e_i)^T P-(e_j) for the unit quaternions e_i: P+(a)^T P-(b) is bilinear in a and b.
_CROSS_TERMS = np.array([[quat.plus_matrix(np.eye(4)[i:i + 1])[0].T
                          @ quat.minus_matrix(np.eye(4)[j:j + 1])[0]
                          for j in range(4)] for i in range(4)])


class MotionSystem:
    """
    Incremental normal matrix M = sum_k B_k^T B_k and its minimum-eigenvector solution.

    For unit p_a, p_b the plus and minus matrices are orthogonal, so
    B^T B = 2 I - (P+(p_a)^T P-(p_b) + its transpose), and the sum over motions needs only
    C = sum_k p_ak p_bk^T (4x4): adding K motions costs one K x 4 x 4 product.
    """

    def __init__(self):
        self.normal_matrix = np.zeros((4, 4))
        self.count = 0

    def add(self, q_a, q_b, reference=None):
        """Add one motion (or a (K, 4) batch of motions): O(1) per motion."""
        q_a = np.asarray(q_a, dtype=float).reshape(-1, 4)
        C = q_a.T @ aligned_b(q_a, q_b, reference)
        S = (C.reshape(16) @ _CROSS_TERMS.reshape(16, 16)).reshape(4, 4)
        self.normal_matrix += 2.0 * len(q_a) * np.eye(4) - S - S.T
        self.count += len(q_a)

    def copy(self):
        """Return an independent duplicate: the system is mutable."""
        other = MotionSystem()
        other.normal_matrix = self.normal_matrix.copy()
        other.count = self.count
        return other

    def solve(self):
        """(p_z (w, x, y, z) with w >= 0, eigenvalues of M ascending)."""
        values, vectors = np.linalg.eigh(self.normal_matrix)
        return quat.canonical(vectors[:, 0]), values


def null_vectors(normals, start, iterations=4):
    """
    Return the eigenvectors of the smallest eigenvalues of normal matrices (H, 4, 4), (H, 4).

    Inverse iteration from `start` (4,): each normal matrix M_h = sum B_k^T B_k of eq. (41) is
    positive semi-definite with a smallest eigenvalue near zero (the noise), well apart from
    the others when its motions' axes differ; (M_h + eps I)^-1, eps a 1e-9 of its trace, turns
    that gap into a factor of 1e-4 or less per iteration. A vector that still moves by more
    than 1e-12 in the last iteration (a small gap: nearly parallel axes, large noise) is
    taken from np.linalg.eigh, which does the same for each 4x4 in turn at several times the
    cost.
    """
    trace = np.trace(normals, axis1=1, axis2=2)
    inverse = np.linalg.inv(normals + (1e-9 * trace + 1e-300)[:, None, None] * np.eye(4))
    vector = inverse @ np.asarray(start, dtype=float)
    last = None
    for _ in range(iterations):   # (the inverse is positive definite: no sign flips)
        last = vector / np.sqrt(np.einsum('hi,hi->h', vector, vector))[:, None]
        vector = (inverse @ last[..., None])[..., 0]
    vector = vector / np.sqrt(np.einsum('hi,hi->h', vector, vector))[:, None]
    moving = np.flatnonzero(np.abs(vector - last).max(axis=1) > 1e-12)
    if len(moving):
        vector[moving] = np.linalg.eigh(normals[moving])[1][:, :, 0]
    return vector


def least_squares_rotation(q_a, q_b, reference=None):
    """p_z minimising sum_k |B_k p_z|^2 over the motions (q_a, q_b) (K, 4) each."""
    system = MotionSystem()
    system.add(q_a, q_b, reference)
    return system.solve()[0]


# --- all pairs in O(N) ------------------------------------------------------------------------

# Samples tried as the anchor of hemisphere_signs.
ANCHORS = 64


def all_pairs_rotation(rotations, use, reference=None, weights=None, iterations=3,
                       anchors=ANCHORS):
    """
    Return the all-pairs least-squares p_z of eq. (41) over the samples `use`, in O(N).

    With sigma_i = +-1 putting every Z_i = A_i p on one hemisphere (erratum 3's sign),
        sum_{i<j} |sigma_j Z_j - sigma_i Z_i|^2 = N^2 - |(sum_i sigma_i A_i) p|^2,
    so the minimiser is the top right singular vector of the 4x4 sum_i sigma_i A_i: no motion
    is formed. The signs come from `reference` (an estimate of p_z) or, without one, from the
    samples alone (hemisphere_signs, up to `anchors` samples tried as the anchor); they are
    then re-decided against the mean sum_i sigma_i Z_i of the new estimate until they stop
    changing (`iterations` at most).
    `weights` (per sample, optional) weigh pair (i, j) by w_i w_j. Returns p_z (w, x, y, z),
    w >= 0.
    """
    A = rotations.matrices[use]
    w = np.ones(len(A)) if weights is None else np.asarray(weights, dtype=float)[use]
    if reference is None:
        signs = hemisphere_signs(rotations.link[use], rotations.sensor[use], anchors)
    else:
        Z = A @ np.asarray(reference, dtype=float)
        signs = np.where(Z @ quat.average(Z, w) < 0.0, -1.0, 1.0)
    flat = A.reshape(-1, 16)
    for _ in range(iterations):
        S = ((w * signs) @ flat).reshape(4, 4)
        p = np.linalg.svd(S)[2][0]
        new_signs = np.where((A @ p) @ (S @ p) < 0.0, -1.0, 1.0)   # S p: the signed sum of Z_i
        if np.array_equal(new_signs, signs):
            break
        signs = new_signs
    return quat.canonical(p)


def hemisphere_signs(link, sensor, anchors=ANCHORS):
    """
    Return the signs sigma_i (N,) that put every Z_i = A_i p_z on one hemisphere, without p_z.

    The motion (k, i) has the scalar parts a_0 = link_k . link_i and b_0 = sensor_k . sensor_i,
    and erratum 3's sign rule a_0 b_0 >= 0 makes Z_i = sign(a_0 b_0) Z_k: the signs against the
    sample k whose products are farthest from zero (a motion near a half turn decides nothing),
    among up to `anchors` samples spread over the set (O(N) memory).
    """
    n = len(link)
    if n <= anchors:
        products = (link @ link.T) * (sensor @ sensor.T)                  # (N, N)
    else:
        tried = np.linspace(0, n - 1, anchors).astype(int)                # (distinct)
        products = (link[tried] @ link.T) * (sensor[tried] @ sensor.T)    # (anchors, N)
    anchor = int(np.argmax(np.abs(products).min(axis=1)))
    return np.where(products[anchor] < 0.0, -1.0, 1.0)
