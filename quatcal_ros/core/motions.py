"""
Motions (A_a, A_b) from still samples, eq. (35)-(36), vectorised over sample pairs.

Eye-in-hand (sensor on the link): with link poses L_i = T_base_link and sensor poses
S_i = T_sensor_obj, the motion between samples i and j is
    A_a = inv(L_i) L_j   (eq. (35), the link's motion in the link frame)
    A_b = S_i inv(S_j)   (eq. (36), the same motion seen in the sensor frame)
and A_a A_z = A_z A_b with A_z the rotation of T_link_sensor.
Eye-to-hand (sensor fixed, object on the link) is the same problem with every link pose
inverted; the answer is then the rotation of T_base_sensor.

Quaternions are (w, x, y, z).
"""

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.units import SETUPS

PAIRINGS = ('all', 'consecutive')


@dataclass(frozen=True)
class SampleRotations:
    """
    The orientations of a sample set, in the form the motions need.

    link: (N, 4) link rotations, inverted for eye-to-hand so that every setup reads
        A_a = inv(link_i) link_j;  sensor: (N, 4) sensor rotations (object in sensor frame);
    link_matrices: (N, 3, 3) the link rotations as matrices (computed when not given).
    """

    link: np.ndarray
    sensor: np.ndarray
    link_inverted: bool = False
    sensor_inverted: bool = False
    link_matrices: np.ndarray = None

    def __post_init__(self):
        if self.link_matrices is None:
            object.__setattr__(self, 'link_matrices', quat.matrix_from_quaternion(self.link))

    @staticmethod
    def from_samples(samples, setup='eye_in_hand', invert_sensor=False):
        """Collect the orientations of `samples` for `setup` (see module docstring)."""
        return SampleRotations.from_arrays(
            np.array([s.link.quaternion for s in samples], dtype=float).reshape(-1, 4),
            np.array([s.sensor.quaternion for s in samples], dtype=float).reshape(-1, 4),
            setup, invert_sensor)

    @staticmethod
    def from_arrays(link, sensor, setup='eye_in_hand', invert_sensor=False):
        """Return from_samples' result for the samples' link and sensor quaternions (N, 4)."""
        if setup not in SETUPS:
            raise ValueError(f'setup must be one of {SETUPS}, not {setup!r}')
        eye_to_hand = setup == 'eye_to_hand'
        if eye_to_hand:
            link = quat.conjugate(link)
        if invert_sensor:
            sensor = quat.conjugate(sensor)
        return SampleRotations(link, sensor, eye_to_hand, bool(invert_sensor))

    def __len__(self):
        return len(self.link)

    @cached_property
    def matrices(self):
        """
        Return A_i = P+(link_i) P-(sensor_i) (N, 4, 4): Z_i = A_i p_z (object_orientations).

        A_i is orthogonal (a product of two orthogonal matrices), so |Z_j - Z_i| = |B_ij p_z|
        for the motion (i, j) of eq. (41) with its sign (erratum 3) chosen to match.
        """
        matrices = quat.plus_matrix(self.link) @ quat.minus_matrix(self.sensor)
        matrices.flags.writeable = False   # remembered: callers share it
        return matrices

    def object_orientations(self, q_z):
        """
        Z_i = link_i (x) q_z (x) sensor_i: the object's orientation in the base frame.

        Constant for noise-free data; the spread of Z_i measures each sample's error. q_z of
        shape (..., 4) gives (..., N, 4): every sample's Z_i for each rotation.
        """
        return (self.matrices @ np.asarray(q_z, dtype=float)[..., None, :, None])[..., 0]


def pair_indices(n, pairing='all'):
    """Return index arrays (i, j), i < j, of the motions formed from n samples."""
    if pairing == 'consecutive':
        first = np.arange(max(n - 1, 0))
        return first, first + 1
    if pairing == 'all':
        return _all_pairs(n)
    raise ValueError(f'pairing must be one of {PAIRINGS}, not {pairing!r}')


@lru_cache(maxsize=8)
def _all_pairs(n):
    """Return np.triu_indices(n, 1), read-only (a live session asks for the same n again)."""
    i, j = np.triu_indices(n, k=1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def pair_angles(q):
    """
    Return the rotation angles between every two of the quaternions q (N, 4): (N, N).

    The angle of inv(q_i) q_j is 2 acos |q_i . q_j|: the dot product is the cosine of half the
    angle between them, so one N x N product gives every pair's motion angle.
    """
    return 2.0 * np.arccos(np.minimum(np.abs(q @ q.T), 1.0))


def motion_count(n, pairing='all'):
    """Return how many motions n samples form (the length of pair_indices(n, pairing))."""
    return n * (n - 1) // 2 if pairing == 'all' else max(n - 1, 0)


@dataclass(frozen=True)
class Motions:
    """Motions k = (i[k], j[k]) with their quaternions q_a, q_b (K, 4), eq. (35)-(36)."""

    i: np.ndarray
    j: np.ndarray
    q_a: np.ndarray
    q_b: np.ndarray

    @staticmethod
    def between(rotations, i, j):
        """Form the motions from sample i[k] to sample j[k]."""
        i = np.asarray(i, dtype=int)
        j = np.asarray(j, dtype=int)
        q_a = quat.multiply(quat.conjugate(rotations.link[i]), rotations.link[j])
        q_b = quat.multiply(rotations.sensor[i], quat.conjugate(rotations.sensor[j]))
        return Motions(i, j, q_a, q_b)

    def __len__(self):
        return len(self.i)

    @staticmethod
    def concatenate(first, second):
        """Join the motions of `first` and those of `second`."""
        return Motions(*(np.concatenate([a, b]) for a, b in zip(
            (first.i, first.j, first.q_a, first.q_b),
            (second.i, second.j, second.q_a, second.q_b))))

    def subset(self, mask):
        """Select the motions where `mask` (bool or index array) says."""
        return Motions(self.i[mask], self.j[mask], self.q_a[mask], self.q_b[mask])

    @property
    def angle_a(self):
        """Rotation angles of A_a (radians, in [0, pi])."""
        return quat.rotation_angle(self.q_a)

    @property
    def angle_b(self):
        """Rotation angles of A_b (radians, in [0, pi])."""
        return quat.rotation_angle(self.q_b)

    def residual_angles(self, q_z):
        """Angle (radians) by which each motion violates p_a (x) p_z = p_z (x) p_b, eq. (38)."""
        left = quat.multiply(self.q_a, q_z)
        right = quat.multiply(q_z, self.q_b)
        return quat.angle_between(left, right)
