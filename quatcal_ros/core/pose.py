"""
Rigid transforms and still samples, the plain-number types the core works on.

A `Pose` T_parent_child holds the position of the child origin in the parent frame (metres)
and the child's orientation as a unit quaternion (w, x, y, z): it maps child coordinates to
parent coordinates, x_parent = R x_child + t. A pose may carry the covariance its source gave
(geometry_msgs/PoseWithCovariance, the covariance columns of the samples CSV): 6x6 in ROS's
order (x, y, z, rotation about the parent's x, y, z axes), metres and radians; composing or
inverting drops it.
"""

from dataclasses import dataclass

import numpy as np

from quatcal_ros.core import quaternion as quat


@dataclass(frozen=True)
class Pose:
    """Rigid transform T_parent_child: position (3,) in metres, quaternion (w, x, y, z)."""

    position: np.ndarray
    quaternion: np.ndarray
    covariance: np.ndarray = None   # 6x6, ROS order (module docstring), or None

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


# Index of ROS's covariance order (x, y, z, rx, ry, rz) in refine's residual order
# (rotation, then translation).
ROS_TO_RESIDUAL = np.array([3, 4, 5, 0, 1, 2])


def residual_order(covariances):
    """Return covariances (..., 6, 6) in ROS's order re-ordered as (rotation, translation)."""
    c = np.asarray(covariances, dtype=float)
    return c[..., ROS_TO_RESIDUAL[:, None], ROS_TO_RESIDUAL]


def ros_order(covariances):
    """Return covariances (..., 6, 6) in the residual's order as ROS orders them."""
    back = np.argsort(ROS_TO_RESIDUAL)
    return np.asarray(covariances, dtype=float)[..., back[:, None], back]


# A sensor pose's standard deviation below this (metres, radians) is no sensor's: such a
# covariance would weigh its sample by more than 1e18 (subnormal ones overflow the solver).
MIN_SENSOR_SIGMA = 1e-9
# Above this (metres, radians) is no sensor's either: drivers that do not know an axis give
# it a variance of 1e6 or 1e9 (a standard deviation of 1e3 or 3e4), which stays usable; a
# covariance of 1e308 overflowed the averaging and the noise figures.
MAX_SENSOR_SIGMA = 1e6
# The covariance's correlation matrix may not be nearer singular than this (its smallest
# eigenvalue): correlations of +-1 leave a direction with no noise at all.
MIN_CORRELATION_EIGENVALUE = 1e-9


def covariance_form_problem(covariance):
    """Say why a square `covariance` is not finite and symmetric (to 1e-6 relative), or None."""
    c = np.asarray(covariance, dtype=float)
    if not np.all(np.isfinite(c)):
        return 'NaN or inf'
    if not np.allclose(c, c.T, rtol=1e-6, atol=0.0):
        return 'not symmetric'
    return None


def covariance_problem(covariance):
    """
    Say what makes a sensor pose's 6x6 covariance unusable, or return None.

    Usable: of its form (covariance_form_problem), every standard deviation from
    MIN_SENSOR_SIGMA to MAX_SENSOR_SIGMA and its correlations short of singular
    (MIN_CORRELATION_EIGENVALUE):
    then it is positive definite and its inverse, the sample's weight, is bounded.
    """
    problem = covariance_form_problem(covariance)
    if problem:
        return problem
    c = np.asarray(covariance, dtype=float)
    variances = np.diagonal(c)
    if not np.all(variances > 0.0):
        return 'not positive definite (variances must be > 0)'
    if not np.all(variances >= MIN_SENSOR_SIGMA ** 2):
        return (f'nearly singular: a standard deviation of {np.sqrt(variances.min()):.3g}, '
                f'below {MIN_SENSOR_SIGMA:g} (m, rad); no sensor is that exact')
    if not np.all(variances <= MAX_SENSOR_SIGMA ** 2):
        return (f'a standard deviation of {np.sqrt(variances.max()):.3g}, above '
                f'{MAX_SENSOR_SIGMA:g} (m, rad): no sensor is that unsure (a driver that does '
                'not know a covariance sends zeros)')
    sigma = np.sqrt(variances)
    with np.errstate(over='ignore'):   # (an entry of 1e308: inf, refused below)
        correlation = c / np.outer(sigma, sigma)
    if not (np.all(np.abs(correlation) <= 1.0 + 1e-9)   # (inf made eigvalsh fail)
            and np.linalg.eigvalsh(correlation)[0] >= MIN_CORRELATION_EIGENVALUE):
        return 'not positive definite (correlations must lie within -1..1, short of +-1)'
    return None


def inverse_perturbation(R, t):
    """
    Return A (N, 6, 6): a small error (r, d) of poses (R, t) as the error of their inverses.

    Errors in refine's convention: R' = exp(r) R, t' = t + d (rotation vector in the parent
    frame, then translation). To first order the inverse (R^T, -R^T t) is off by
    r_inv = -R^T r and d_inv = -R^T d - R^T [t]x r, so a covariance C of (r, d) becomes
    A C A^T.
    """
    R_T = np.transpose(np.asarray(R, dtype=float), (0, 2, 1))
    A = np.zeros((len(R_T), 6, 6))
    A[:, 0:3, 0:3] = -R_T
    A[:, 3:6, 0:3] = -R_T @ quat.skew(t)
    A[:, 3:6, 3:6] = -R_T
    return A


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
