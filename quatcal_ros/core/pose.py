"""
Rigid transforms and still samples, the plain-number types the core works on.

A `Pose` T_parent_child holds the position of the child origin in the parent frame (metres)
and the child's orientation as a unit quaternion (w, x, y, z): it maps child coordinates to
parent coordinates, x_parent = R x_child + t.
"""

from dataclasses import dataclass

import numpy as np

from quatcal_ros.core import quaternion as quat


@dataclass(frozen=True)
class Pose:
    """Rigid transform T_parent_child: position (3,) in metres, quaternion (w, x, y, z)."""

    position: np.ndarray
    quaternion: np.ndarray

    @staticmethod
    def create(position, quaternion_wxyz):
        """Build from any sequences; the quaternion is normalised."""
        return Pose(np.array(position, dtype=float).reshape(3),
                    quat.normalize(np.array(quaternion_wxyz, dtype=float).reshape(4)))

    @staticmethod
    def identity():
        return Pose(np.zeros(3), quat.IDENTITY.copy())

    @property
    def rotation(self):
        """3x3 rotation matrix of the orientation."""
        return quat.matrix_from_quaternion(self.quaternion)

    def inverse(self):
        """T_child_parent."""
        q_inv = quat.conjugate(self.quaternion)
        return Pose(-quat.matrix_from_quaternion(q_inv) @ self.position, q_inv)

    def __matmul__(self, other):
        """Composition T_a_b @ T_b_c = T_a_c."""
        return Pose(self.position + self.rotation @ other.position,
                    quat.normalize(quat.multiply(self.quaternion, other.quaternion)))

    def as_matrix(self):
        """4x4 homogeneous matrix."""
        H = np.eye(4)
        H[:3, :3] = self.rotation
        H[:3, 3] = self.position
        return H

    @staticmethod
    def from_matrix(H):
        """From a 4x4 homogeneous matrix."""
        H = np.asarray(H, dtype=float)
        return Pose(H[:3, 3].copy(), quat.quaternion_from_matrix(H[:3, :3]))


@dataclass(frozen=True)
class Sample:
    """
    One still sample: both poses at the same instant (header stamp, integer nanoseconds).

    link: T_base_link, the link pose in the robot base frame.
    sensor: T_sensor_obj, the observed fixed object in the sensor frame.
    """

    stamp_ns: int
    link: Pose
    sensor: Pose
