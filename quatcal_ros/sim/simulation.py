"""
Synthetic hand-eye cells with known answers: still samples and time-stamped pose streams.

Used by the tests, the benchmarks, the sim_cell node and the demo.  Core module: standard
library and numpy only.  Quaternions are (w, x, y, z), positions metres, times integer
nanoseconds.  Every random draw comes from the numpy Generator passed in
(np.random.default_rng(seed)), so a seed reproduces everything.

Frames (DESIGN.md conventions; L = T_base_link, S = T_sensor_obj):

- eye_in_hand: the sensor rides on the link at X = T_link_sensor (`Cell.mounting`, the answer);
  the object is fixed at O = T_base_obj (`Cell.target`), so L @ X @ S = O for every pose.
- eye_to_hand: the sensor is fixed at M = T_base_sensor (`Cell.mounting`, the answer); the
  object rides on the link at T = T_link_obj (`Cell.target`), so S = inv(M) @ L @ T.

The arrays below hold many poses at once: positions (N, 3) and quaternions (N, 4).
"""

from dataclasses import dataclass, field
import math

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose, ros_order, Sample
from quatcal_ros.core.units import ns_from_s, NS_PER_S, SETUPS

# A realistic epoch (Nov 2023): float64 cannot hold it to the nanosecond, which catches code
# that turns stamps into floats too early.
DEFAULT_START_NS = 1_700_000_000 * NS_PER_S
# Home link pose: 45 cm in front of the base, 55 cm up, tool z axis pointing down.
HOME_POSITION = (0.45, 0.0, 0.55)
HOME_QUATERNION = (0.0, 1.0, 0.0, 0.0)
OUTLIER_KINDS = ('flip_x', 'flip_y', 'random')
# StopAndGo's robots: a 6-axis arm, or one that cannot turn the link freely (REDUCED_KINDS).
ROBOTS = ('arm', 'scara', 'gantry')
_FLIP_X = np.array([0.0, 1.0, 0.0, 0.0])
_FLIP_Y = np.array([0.0, 0.0, 1.0, 0.0])


def _home_pose():
    return Pose.create(HOME_POSITION, HOME_QUATERNION)


# --- vectorised pose algebra on (N, 3) positions and (N, 4) quaternions -----------------------

def compose(p1, q1, p2, q2):
    """T1 @ T2 for arrays of poses (position, quaternion (w, x, y, z)), broadcasting."""
    return p1 + quat.rotate(q1, p2), quat.multiply(q1, q2)


def invert(p, q):
    """inv(T) for arrays of poses (position, quaternion (w, x, y, z))."""
    q_inv = quat.conjugate(q)
    return -quat.rotate(q_inv, p), q_inv


def minimum_jerk(s):
    """Minimum-jerk time scaling 10 s^3 - 15 s^4 + 6 s^5 of s in [0, 1] (zero end rates)."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


def random_quaternions(rng, n):
    """Return n rotations (w, x, y, z), uniform over SO(3) (normalised 4-D Gaussian), w >= 0."""
    q = quat.normalize(rng.standard_normal((n, 4)))
    return np.where(q[:, :1] < 0.0, -q, q)


def random_unit_vectors(rng, n):
    """Return n unit vectors, uniform on the sphere, shape (n, 3)."""
    return quat.normalize(rng.standard_normal((n, 3)))


def quaternion_wxyz_from_rpy(roll, pitch, yaw):
    """Return (w, x, y, z) of ROS roll, pitch, yaw (radians): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    q_x = quat.from_axis_angle([1.0, 0.0, 0.0], roll)
    q_y = quat.from_axis_angle([0.0, 1.0, 0.0], pitch)
    q_z = quat.from_axis_angle([0.0, 0.0, 1.0], yaw)
    return quat.multiply(q_z, quat.multiply(q_y, q_x))


def poses_from_arrays(positions, quaternions):
    """List of Pose from (N, 3) positions and (N, 4) unit quaternions (w, x, y, z)."""
    positions = np.array(positions, dtype=float)
    quaternions = np.array(quaternions, dtype=float)
    return [Pose(p, q) for p, q in zip(positions, quaternions)]


def _stack(poses):
    return (np.array([p.position for p in poses], dtype=float).reshape(-1, 3),
            np.array([p.quaternion for p in poses], dtype=float).reshape(-1, 4))


# --- the cell --------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Cell:
    """
    A hand-eye cell with a known answer (see the module docstring for the frames).

    mounting: the answer; T_link_sensor (eye_in_hand) or T_base_sensor (eye_to_hand).
    target: the observed object; T_base_obj (eye_in_hand) or T_link_obj (eye_to_hand).
    home: T_base_link around which the robot moves; the object faces the sensor there.
    """

    mounting: Pose
    target: Pose
    home: Pose = field(default_factory=_home_pose)
    setup: str = 'eye_in_hand'

    def __post_init__(self):
        if self.setup not in SETUPS:
            raise ValueError(f'setup must be one of {SETUPS}, not {self.setup!r}')

    def sensor_poses(self, link_positions, link_quaternions):
        """Noise-free T_sensor_obj (positions (N, 3), quaternions (N, 4)) for link poses."""
        m_p, m_q = self.mounting.position, self.mounting.quaternion
        t_p, t_q = self.target.position, self.target.quaternion
        if self.setup == 'eye_in_hand':
            # S = inv(L @ X) @ O
            s_p, s_q = invert(*compose(link_positions, link_quaternions, m_p, m_q))
            p, q = compose(s_p, s_q, t_p, t_q)
        else:
            # S = inv(M) @ L @ T
            p, q = compose(*invert(m_p, m_q),
                           *compose(link_positions, link_quaternions, t_p, t_q))
        return p, _positive_w(q)

    def sensor_pose(self, link):
        """Noise-free T_sensor_obj for one link pose T_base_link."""
        p, q = self.sensor_poses(link.position[None], link.quaternion[None])
        return Pose(p[0], q[0])


def _positive_w(q):
    return np.where(q[..., :1] < 0.0, -q, q)


def _facing_rotation(rng, max_tilt_deg=20.0):
    """
    Object orientation in the sensor frame when it faces the sensor (marker z to camera).

    Rx(180 deg), then a tilt of up to max_tilt_deg about an in-plane axis and a random spin
    about the marker normal.
    """
    tilt_axis = np.append(random_unit_vectors(rng, 1)[0, :2], 0.0)
    tilt = quat.from_axis_angle(tilt_axis, np.radians(rng.uniform(0.0, max_tilt_deg)))
    spin = quat.from_axis_angle([0.0, 0.0, 1.0], rng.uniform(-np.pi, np.pi))
    return quat.multiply(_FLIP_X, quat.multiply(tilt, spin))


def _object_in_front(rng):
    """T_sensor_obj of an object 0.5-1 m in front of the sensor, facing it."""
    position = [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.5, 1.0)]
    return Pose.create(position, _facing_rotation(rng))


def _look_at(rng, eye, point):
    """T_base_sensor at `eye` with its z (optical) axis towards `point`, random roll."""
    z = quat.normalize(np.asarray(point) - np.asarray(eye))
    x = np.cross(z, random_unit_vectors(rng, 1)[0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    return Pose(np.asarray(eye, dtype=float), quat.quaternion_from_matrix(R))


def random_mounting_eye_in_hand(rng):
    """T_link_sensor: a uniformly random rotation, 5-15 cm from the link origin."""
    offset = random_unit_vectors(rng, 1)[0] * rng.uniform(0.05, 0.15)
    return Pose(offset, random_quaternions(rng, 1)[0])


def random_cell(rng, setup='eye_in_hand', mounting=None, home=None):
    """
    Return a random Cell; `mounting` (a Pose) fixes the answer instead of drawing it.

    eye_in_hand: mounting is a random rotation, 5-15 cm from the link origin; the object is
    0.5-1 m in front of the sensor at the home pose, facing it (tilted up to 20 deg).
    eye_to_hand: the object sits 5-15 cm from the link origin; the sensor is 0.5-1 m from it
    at home, looking at it from above with a random roll.  With a given mounting the home
    position is moved so that the object is 0.5-1 m in front of that sensor.
    """
    if setup not in SETUPS:
        raise ValueError(f'setup must be one of {SETUPS}, not {setup!r}')
    home = _home_pose() if home is None else home
    if setup == 'eye_in_hand':
        if mounting is None:
            mounting = random_mounting_eye_in_hand(rng)
        target = home @ mounting @ _object_in_front(rng)
        return Cell(mounting=mounting, target=target, home=home, setup=setup)
    object_offset = random_unit_vectors(rng, 1)[0] * rng.uniform(0.05, 0.15)
    if mounting is None:
        object_home = home.position + home.rotation @ object_offset
        view = random_unit_vectors(rng, 1)[0]
        view[2] = abs(view[2]) + 0.5   # look from above
        eye = object_home + quat.normalize(view) * rng.uniform(0.5, 1.0)
        mounting = _look_at(rng, eye, object_home)
        base_obj = Pose(object_home,
                        quat.multiply(mounting.quaternion, _facing_rotation(rng)))
    else:
        base_obj = mounting @ _object_in_front(rng)
        home = Pose(base_obj.position - home.rotation @ object_offset, home.quaternion)
    link_obj = Pose(object_offset, quat.normalize(
        quat.multiply(quat.conjugate(home.quaternion), base_obj.quaternion)))
    return Cell(mounting=mounting, target=link_obj, home=home, setup=setup)


# --- robot poses -----------------------------------------------------------------------------

def _in_view(positions, quaternions, max_view_angle_deg, max_incidence_deg,
             min_distance_m=0.2):
    """Whether a camera at the sensor frame sees the object (a marker), per T_sensor_obj."""
    distance = np.linalg.norm(positions, axis=-1)
    off_axis = np.arccos(np.clip(positions[:, 2] / distance, -1.0, 1.0))
    normal = quat.rotate(quaternions, np.array([0.0, 0.0, 1.0]))
    facing = -np.sum(normal * positions, axis=-1) / distance
    incidence = np.arccos(np.clip(facing, -1.0, 1.0))
    return ((distance >= min_distance_m) & (off_axis <= np.radians(max_view_angle_deg))
            & (incidence <= np.radians(max_incidence_deg)))


def stop_poses(rng, cell, n, rotation_spread_deg=30.0, translation_range_m=(0.10, 0.20),
               max_view_angle_deg=45.0, max_incidence_deg=65.0, max_tries=1000):
    """
    Return n link poses T_base_link around cell.home from which the sensor sees the object.

    Each pose turns the home pose about a random axis by an angle drawn uniformly from
    [0, rotation_spread_deg], about a pivot that keeps the object in view (the sensor origin for
    eye_in_hand, the object origin for eye_to_hand), then shifts it by translation_range_m
    (metres, uniform) in a random direction.  Poses are redrawn until the object is at most
    max_view_angle_deg off the optical (z) axis and the marker normal at most
    max_incidence_deg from the line of sight; ValueError after max_tries rounds of draws.
    """
    home = cell.home
    pivot_link = cell.mounting.position if cell.setup == 'eye_in_hand' else cell.target.position
    pivot = home.position + home.rotation @ pivot_link
    positions, quaternions = np.empty((0, 3)), np.empty((0, 4))
    for _ in range(max_tries):
        m = int(n) - len(positions)
        if m <= 0:
            return poses_from_arrays(positions, quaternions)
        angles = np.radians(rng.uniform(0.0, rotation_spread_deg, m))
        turns = quat.from_rotation_vector(random_unit_vectors(rng, m) * angles[:, None])
        shifts = random_unit_vectors(rng, m) * rng.uniform(*translation_range_m, m)[:, None]
        link_p = pivot + quat.rotate(turns, home.position - pivot) + shifts
        link_q = quat.normalize(quat.multiply(turns, home.quaternion))
        seen = _in_view(*cell.sensor_poses(link_p, link_q), max_view_angle_deg,
                        max_incidence_deg)
        positions = np.concatenate([positions, link_p[seen]])
        quaternions = np.concatenate([quaternions, link_q[seen]])
    raise ValueError(
        f'no stop pose with the object in view after {max_tries} rounds of draws: reduce '
        f'rotation_spread_deg ({rotation_spread_deg}) or translation_range_m '
        f'({translation_range_m}), or widen max_view_angle_deg ({max_view_angle_deg})')


# --- what a sensor reports -------------------------------------------------------------------

def add_pose_noise(rng, positions, quaternions, rotation_noise_deg=0.0, translation_noise_m=0.0):
    """
    Noisy copies of poses: q' = exp(r) (x) q, p' = p + t, with r, t ~ N(0, sigma^2 I).

    r is a rotation vector (radians, std rotation_noise_deg per axis) applied in the parent
    frame; t has std translation_noise_m (metres) per axis.  Draws (N, 6) standard normals in
    row order even at zero noise, so batches of frames give the same result as one call.
    """
    if rotation_noise_deg < 0.0 or translation_noise_m < 0.0:
        raise ValueError('noise standard deviations must be >= 0')
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    quaternions = np.asarray(quaternions, dtype=float).reshape(-1, 4)
    z = rng.standard_normal((len(positions), 6))
    turn = quat.from_rotation_vector(z[:, :3] * np.radians(rotation_noise_deg))
    noisy_q = _positive_w(quat.normalize(quat.multiply(turn, quaternions)))
    return positions + z[:, 3:] * translation_noise_m, noisy_q


def robot_reported(rng, links, rotation_deg, translation_mm):
    """
    Return the poses a robot reports for the true link poses `links` (Poses).

    Each is off by its own draw of add_pose_noise, of RMS rotation_deg and translation_mm
    (angle and length; the standard deviation per axis is that over sqrt(3)).
    """
    positions, quaternions = add_pose_noise(
        rng, [link.position for link in links], [link.quaternion for link in links],
        rotation_deg / math.sqrt(3.0), 1e-3 * translation_mm / math.sqrt(3.0))
    return [Pose(p, q) for p, q in zip(positions, quaternions)]


def add_sensor_noise(rng, positions, quaternions, covariance):
    """
    Noisy copies of sensor poses with a 6x6 covariance in the sensor frame.

    Draws e ~ N(0, covariance) per pose, e = (rotation vector r in radians, translation t in
    metres), and returns p' = p + t, q' = exp(r) (x) q: the error model of refine.py's
    residual (rotation vector of R_meas R_true^T, t_meas - t_true). covariance: one 6x6 for
    all poses, or one per pose (N, 6, 6).
    """
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    quaternions = np.asarray(quaternions, dtype=float).reshape(-1, 4)
    root = np.broadcast_to(np.linalg.cholesky(covariance), (len(positions), 6, 6))
    e = np.einsum('nab,nb->na', root, rng.standard_normal((len(positions), 6)))
    turn = quat.from_rotation_vector(e[:, :3])
    return positions + e[:, 3:], _positive_w(quat.normalize(quat.multiply(turn, quaternions)))


def pnp_like_covariance(lateral_m=0.0005, depth_m=0.003, rotation_deg=0.1,
                        rotation_about_axis_deg=0.03, correlation=0.8):
    """
    Return a 6x6 sensor-frame covariance shaped like camera poses from PnP.

    Position noise along the optical axis (sensor z) is depth_m, across it lateral_m;
    rotation noise about the lateral axes rotation_deg, about the optical axis
    rotation_about_axis_deg. A tilt of the target about x is confused with a shift along y
    (and about y with one along x), which the correlation models.
    """
    r, rz = np.radians(rotation_deg), np.radians(rotation_about_axis_deg)
    sd = np.array([r, r, rz, lateral_m, lateral_m, depth_m])
    correlation_matrix = np.eye(6)
    correlation_matrix[0, 4] = correlation_matrix[4, 0] = correlation
    correlation_matrix[1, 3] = correlation_matrix[3, 1] = -correlation
    return correlation_matrix * np.outer(sd, sd)


def corrupt_orientations(quaternions, uniforms):
    """
    Bad detections of T_sensor_obj orientations (N, 4), as marker detectors make them.

    Row i of `uniforms` (N, 4) in [0, 1) picks the kind OUTLIER_KINDS[floor(3 u0)]:
    'flip_x' / 'flip_y' turn the object by 180 deg about its own x / y axis (q (x) R);
    'random' applies a rotation by 30-180 deg (u3) about a random axis (u1, u2).
    Returns (quaternions (N, 4), kinds (list of str)).
    """
    q = np.array(quaternions, dtype=float).reshape(-1, 4)
    u = np.asarray(uniforms, dtype=float).reshape(-1, 4)
    kind = np.minimum((u[:, 0] * 3.0).astype(int), 2)
    z = 2.0 * u[:, 1] - 1.0
    phi = 2.0 * np.pi * u[:, 2]
    r = np.sqrt(1.0 - z * z)
    axes = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    angles = np.radians(30.0 + 150.0 * u[:, 3])
    random_turn = quat.from_rotation_vector(axes * angles[:, None])
    out = np.where((kind == 0)[:, None], quat.multiply(q, _FLIP_X), q)
    out = np.where((kind == 1)[:, None], quat.multiply(q, _FLIP_Y), out)
    out = np.where((kind == 2)[:, None], quat.multiply(random_turn, q), out)
    return _positive_w(out), [OUTLIER_KINDS[k] for k in kind]


def scaled_sensor_positions(samples, scale, inverted=False):
    """
    Return the samples as a sensor with a scale error reports them (core/sensor_scale.py).

    The object's position in the sensor frame multiplied by `scale` (per sensor axis): a
    marker or board size off by a factor scales all three, a focal length the depth (z).
    inverted: the sensor poses are the sensor in the object frame (invert_sensor); their
    inverses are scaled.
    """
    def scaled(pose):
        return Pose(pose.position * np.asarray(scale), pose.quaternion, pose.covariance)
    return [Sample(s.stamp_ns, s.link, scaled(s.sensor.inverse()).inverse() if inverted
                   else scaled(s.sensor)) for s in samples]


def samples(rng, cell, n, rotation_noise_deg=0.0, translation_noise_m=0.0, outlier_fraction=0.0,
            link_rotation_noise_deg=0.0, link_translation_noise_m=0.0, rotation_spread_deg=30.0,
            start_ns=DEFAULT_START_NS, period_ns=2 * NS_PER_S, sensor_covariance=None,
            report_covariance=False, tail_nu=math.inf):
    """
    Return n still samples of `cell` at stop_poses(), and the indices of the outliers.

    Sensor poses T_sensor_obj get add_pose_noise(rotation_noise_deg, translation_noise_m);
    round(outlier_fraction * n) of them, at random indices, are then corrupted
    (corrupt_orientations); link poses get link_rotation_noise_deg / link_translation_noise_m.
    Stamps are start_ns + i * period_ns (int).  The stops and the outlier indices do not depend
    on the noise levels.  sensor_covariance (6x6, e.g. pnp_like_covariance(), or one per
    sample, (n, 6, 6)) replaces the two sensor noise levels by add_sensor_noise; with
    report_covariance the sensor poses carry it (Pose.covariance, ROS order), as a detector
    that publishes PoseWithCovarianceStamped would. A finite tail_nu makes the sensor noise
    heavy-tailed, a Student t with tail_nu degrees of freedom: each pose's covariance is
    scaled by tail_nu / chi2(tail_nu) (a few poses far noisier than the rest).
    Returns (list[Sample], sorted list[int] of outlier indices).
    """
    if not 0.0 <= outlier_fraction <= 1.0:
        raise ValueError(f'outlier_fraction must be in [0, 1], not {outlier_fraction}')
    link_p, link_q = _stack(stop_poses(rng, cell, n, rotation_spread_deg))
    if math.isfinite(tail_nu):
        if sensor_covariance is None:
            sensor_covariance = np.diag(np.square([np.radians(rotation_noise_deg)] * 3
                                                  + [translation_noise_m] * 3))
        scales = tail_nu / rng.chisquare(tail_nu, n)
        sensor_covariance = np.broadcast_to(sensor_covariance, (n, 6, 6)) * scales[:, None, None]
    if sensor_covariance is None:
        sensor_p, sensor_q = add_pose_noise(rng, *cell.sensor_poses(link_p, link_q),
                                            rotation_noise_deg, translation_noise_m)
    else:
        sensor_p, sensor_q = add_sensor_noise(rng, *cell.sensor_poses(link_p, link_q),
                                              sensor_covariance)
    outliers = np.sort(rng.choice(n, int(round(outlier_fraction * n)), replace=False))
    sensor_q[outliers], _ = corrupt_orientations(sensor_q[outliers],
                                                 rng.random((len(outliers), 4)))
    link_p, link_q = add_pose_noise(rng, link_p, link_q,
                                    link_rotation_noise_deg, link_translation_noise_m)
    reported = [None] * n
    if report_covariance and sensor_covariance is not None:
        reported = list(np.broadcast_to(ros_order(sensor_covariance), (n, 6, 6)).copy())
    result = [Sample(int(start_ns) + i * int(period_ns), Pose(link_p[i], link_q[i]),
                     Pose(sensor_p[i], sensor_q[i], reported[i])) for i in range(n)]
    return result, [int(i) for i in outliers]


class SensorModel:
    """
    What a camera with a marker detector reports for true T_sensor_obj: noise, drops, flips.

    Noise, drops and outliers come from three generators spawned from rng, each drawn frame by
    frame with a fixed number of draws per frame, so a frame's fate does not depend on how
    frames are batched (the node observes a few per timer tick, stop_and_go_streams all at
    once).  Outliers (probability outlier_fraction per frame) are corrupt_orientations().
    """

    def __init__(self, rng, rotation_noise_deg=0.0, translation_noise_m=0.0,
                 drop_probability=0.0, outlier_fraction=0.0):
        for name, value in (('drop_probability', drop_probability),
                            ('outlier_fraction', outlier_fraction)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f'{name} must be in [0, 1], not {value}')
        self._noise_rng, self._drop_rng, self._outlier_rng = rng.spawn(3)
        self.rotation_noise_deg = float(rotation_noise_deg)
        self.translation_noise_m = float(translation_noise_m)
        self.drop_probability = float(drop_probability)
        self.outlier_fraction = float(outlier_fraction)

    def observe(self, positions, quaternions):
        """
        Report poses for true ones, (N, 3) and (N, 4).

        Returns (positions, quaternions, kept, outlier): kept[i] is False for a dropped frame,
        outlier[i] True for a corrupted orientation.
        """
        p, q = add_pose_noise(self._noise_rng, positions, quaternions,
                              self.rotation_noise_deg, self.translation_noise_m)
        kept = self._drop_rng.random(len(p)) >= self.drop_probability
        u = self._outlier_rng.random((len(p), 5))
        outlier = u[:, 0] < self.outlier_fraction
        q[outlier], _ = corrupt_orientations(q[outlier], u[outlier, 1:])
        return p, q, kept, outlier


# --- stop-and-go trajectories and time-stamped streams ---------------------------------------

def grid_times_ns(indices, rate_hz):
    """Return times (int64 ns from 0) of samples `indices` at rate_hz: rint(i * 1e9 / rate)."""
    return np.rint(np.asarray(indices, dtype=float) * (NS_PER_S / rate_hz)).astype(np.int64)


def last_grid_index(t_ns, rate_hz):
    """Largest i (>= -1) with grid_times_ns(i, rate_hz) <= t_ns."""
    if t_ns < 0:
        return -1
    i = int(np.floor(t_ns * rate_hz / NS_PER_S))
    while grid_times_ns(i + 1, rate_hz) <= t_ns:
        i += 1
    while i >= 0 and grid_times_ns(i, rate_hz) > t_ns:
        i -= 1
    return i


class StopAndGo:
    """
    A robot that stands still at each stop for still_s, then moves to the next in move_s.

    robot 'arm' visits stop_poses(); 'scara' and 'gantry' reduced_dof_poses() (turns about base
    z of up to rotation_spread_deg, or none).

    Stops k = 0, 1, ... are stop_poses() of the cell, drawn one at a time (when first needed)
    from a generator spawned from rng.  Times t_ns are integer nanoseconds since the start:
    stop k is held during [k P, k P + still) with P = still + move; the move to stop k + 1
    follows, SLERP in orientation and a straight line in position, both with minimum-jerk
    timing.  n_stops = 0 runs forever; otherwise the robot holds the last stop from
    k = n_stops - 1 on.  max_view_angle_deg, max_incidence_deg: stop_poses' (every robot's
    stops are redrawn until the sensor sees the object so).
    """

    def __init__(self, rng, cell, still_s=1.5, move_s=2.0, n_stops=0, rotation_spread_deg=30.0,
                 robot='arm', max_view_angle_deg=45.0, max_incidence_deg=65.0):
        if robot not in ROBOTS:
            raise ValueError(f'robot must be one of {ROBOTS}, not {robot!r}')
        if still_s < 0.0 or move_s <= 0.0:
            raise ValueError(f'need still_s >= 0 and move_s > 0, not {still_s}, {move_s}')
        if n_stops < 0:
            raise ValueError(f'n_stops must be >= 0 (0 = forever), not {n_stops}')
        self.cell = cell
        self.still_ns = ns_from_s(still_s)
        self.move_ns = ns_from_s(move_s)
        self.period_ns = self.still_ns + self.move_ns
        self.n_stops = int(n_stops)
        self.rotation_spread_deg = rotation_spread_deg
        self.robot = robot
        self.view = {'max_view_angle_deg': max_view_angle_deg,
                     'max_incidence_deg': max_incidence_deg}
        self._rng = rng.spawn(1)[0]
        self._positions = np.empty((0, 3))
        self._quaternions = np.empty((0, 4))

    @property
    def duration_ns(self):
        """End of the last stop's still interval (None when running forever)."""
        if self.n_stops == 0:
            return None
        return self.n_stops * self.period_ns - self.move_ns

    def _ensure(self, count):
        new = count - len(self._positions)
        if new > 0 and self.robot != 'arm':
            p, q = _stack([self._reduced_dof_stop() for _ in range(new)])
        elif new > 0:
            p, q = _stack([stop_poses(self._rng, self.cell, 1, self.rotation_spread_deg,
                                      **self.view)[0] for _ in range(new)])
        if new > 0:
            self._positions = np.concatenate([self._positions, p])
            self._quaternions = np.concatenate([self._quaternions, q])

    def _reduced_dof_stop(self, max_tries=1000):
        """Return a reduced_dof_poses() stop from which the sensor sees the object (`view`)."""
        for _ in range(max_tries):
            p, q = reduced_dof_poses(self._rng, self.cell, 1, self.robot,
                                     turn_deg=self.rotation_spread_deg)
            if _in_view(*self.cell.sensor_poses(p, q), **self.view)[0]:
                return Pose(p[0], q[0])
        raise ValueError(f'no {self.robot} stop with the object in view after {max_tries} '
                         f'draws: reduce rotation_spread_deg ({self.rotation_spread_deg}) or '
                         f'widen max_view_angle_deg ({self.view["max_view_angle_deg"]})')

    def stop(self, k):
        """T_base_link of stop k."""
        self._ensure(k + 1)
        return Pose(self._positions[k].copy(), self._quaternions[k].copy())

    def still_interval_ns(self, k):
        """(first, last) time (ns since start) of the still interval at stop k."""
        start = k * self.period_ns
        return start, start + self.still_ns

    def segments(self, t_ns):
        """
        Return where times t_ns are: the stop k left last, the next one, and the fraction s.

        s in [0, 1] of the move from k to the next by minimum-jerk timing (0 while still).
        """
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        k = np.maximum(t, 0) // self.period_ns
        fraction = (t - k * self.period_ns - self.still_ns) / self.move_ns
        following = k + 1
        if self.n_stops:
            last = self.n_stops - 1
            fraction = np.where(k >= last, 0.0, fraction)
            k = np.minimum(k, last)
            following = np.minimum(following, last)
        return k, following, minimum_jerk(fraction)

    def is_still(self, t_ns):
        """Whether the robot stands still at times t_ns (bool array)."""
        return self.segments(t_ns)[2] == 0.0

    def link_poses(self, t_ns):
        """T_base_link at times t_ns (int, ns since start): positions (N, 3), quats (N, 4)."""
        k, following, s = self.segments(t_ns)
        if len(k) == 0:
            return np.empty((0, 3)), np.empty((0, 4))
        self._ensure(int(following.max()) + 1)
        p0, p1 = self._positions[k], self._positions[following]
        q0, q1 = self._quaternions[k], self._quaternions[following]
        positions = p0 + s[:, None] * (p1 - p0)
        quaternions = np.where((s == 0.0)[:, None], q0, quat.slerp(q0, q1, s))
        return positions, quaternions


@dataclass(frozen=True, eq=False)
class Streams:
    """
    Time-stamped poses of a stop-and-go run, with the truth.

    link: [(stamp_ns, T_base_link)] at the link rate, header stamps.
    sensor: [(stamp_ns, T_sensor_obj)] of the frames not dropped; the stamp is the exposure
    time, and sensor_delivery_ns[i] (stamp + latency) when the frame is published.
    sensor_outliers: indices into `sensor` of corrupted orientations.
    stops: T_base_link of each stop; stills: (first_ns, last_ns) of each still interval.
    """

    cell: Cell
    link: list
    sensor: list
    sensor_delivery_ns: list
    sensor_outliers: list
    stops: list
    stills: list

    @property
    def truth(self):
        """Return the answer: cell.mounting (T_link_sensor, or T_base_sensor for eye_to_hand)."""
        return self.cell.mounting

    def delivery_order(self, names=('link', 'sensor')):
        """
        Return both streams as [(due ns, stream name, header stamp ns, pose)] in publishing order.

        A link pose is due at its stamp, a sensor frame at its delivery; at equal times the
        link pose comes first.  names: what to call the two streams.
        """
        link, sensor = names
        events = [(stamp, 0, link, stamp, pose) for stamp, pose in self.link]
        events += [(due, 1, sensor, stamp, pose)
                   for due, (stamp, pose) in zip(self.sensor_delivery_ns, self.sensor)]
        events.sort(key=lambda event: event[:2])
        return [(due, name, stamp, pose) for due, _, name, stamp, pose in events]


def stop_and_go_streams(rng, cell, n_stops, link_rate_hz=500.0, sensor_rate_hz=30.0,
                        still_s=1.5, move_s=2.0, rotation_noise_deg=0.0,
                        translation_noise_m=0.0, latency_s=0.03, drop_probability=0.05,
                        outlier_fraction=0.0, rotation_spread_deg=30.0,
                        start_ns=DEFAULT_START_NS, clock_offset_s=0.0, robot='arm'):
    """
    Link and sensor streams of a robot visiting n_stops stops (StopAndGo, SensorModel).

    robot: 'arm' (stop_poses), or 'scara' / 'gantry' (reduced_dof_poses: the link turns by up
    to rotation_spread_deg about base z, or not at all).

    Link samples are at start_ns + grid_times_ns(i, link_rate_hz), sensor exposures at
    start_ns + grid_times_ns(j, sensor_rate_hz), both up to the end of the last still interval;
    each frame is delivered latency_s after its exposure.  clock_offset_s: the sensor's clock
    leads the robot's by this much (a clock offset mode): every sensor stamp is its exposure
    time plus the offset, the poses and the delivery times stay the same (the session's
    sensor_time_offset_s = -clock_offset_s undoes it).  The sim_cell node builds the same
    StopAndGo and SensorModel from the same rng in the same order, so with its seed, the same
    cell and start_ns it publishes these very poses.  Vectorised: 10 minutes at 1 kHz take
    about a second.
    """
    if n_stops < 1:
        raise ValueError(f'n_stops must be >= 1, not {n_stops}')
    if latency_s < 0.0 or link_rate_hz <= 0.0 or sensor_rate_hz <= 0.0:
        raise ValueError('need latency_s >= 0 and positive rates')
    trajectory = StopAndGo(rng, cell, still_s, move_s, n_stops, rotation_spread_deg, robot)
    sensor = SensorModel(rng, rotation_noise_deg, translation_noise_m, drop_probability,
                         outlier_fraction)
    end = trajectory.duration_ns
    link_t = grid_times_ns(np.arange(last_grid_index(end, link_rate_hz) + 1), link_rate_hz)
    link_p, link_q = trajectory.link_poses(link_t)
    exposure_t = grid_times_ns(np.arange(last_grid_index(end, sensor_rate_hz) + 1),
                               sensor_rate_hz)
    true_p, true_q = cell.sensor_poses(*trajectory.link_poses(exposure_t))
    sensor_p, sensor_q, kept, outlier = sensor.observe(true_p, true_q)
    start = int(start_ns)
    exposures = exposure_t[kept] + start
    sensor_stamps = (exposures + ns_from_s(clock_offset_s)).tolist()
    return Streams(
        cell=cell,
        link=list(zip((link_t + start).tolist(), poses_from_arrays(link_p, link_q))),
        sensor=list(zip(sensor_stamps, poses_from_arrays(sensor_p[kept], sensor_q[kept]))),
        sensor_delivery_ns=(exposures + ns_from_s(latency_s)).tolist(),
        sensor_outliers=np.flatnonzero(outlier[kept]).tolist(),
        stops=[trajectory.stop(k) for k in range(n_stops)],
        stills=[tuple(start + t for t in trajectory.still_interval_ns(k))
                for k in range(n_stops)])


# --- robots with fewer degrees of freedom -----------------------------------------------------

REDUCED_KINDS = ('scara', 'gantry')


def reduced_dof_poses(rng, cell, n, kind='scara', reach_m=0.15, turn_deg=60.0):
    """Return n link poses (positions (n, 3), quaternions (n, 4)) of reduced_dof_samples."""
    if kind not in REDUCED_KINDS:
        raise ValueError(f'kind must be one of {REDUCED_KINDS}, not {kind!r}')
    positions = np.asarray(cell.home.position) + rng.uniform(-reach_m, reach_m, (n, 3))
    if kind == 'scara':
        turns = np.radians(rng.uniform(-turn_deg, turn_deg, n))
        spins = np.column_stack([np.cos(turns / 2), np.zeros((n, 2)), np.sin(turns / 2)])
        return positions, quat.multiply(spins, np.asarray(cell.home.quaternion)[None])
    return positions, np.repeat(np.asarray(cell.home.quaternion, float)[None], n, axis=0)


def reduced_dof_samples(rng, cell, n, kind='scara', rotation_noise_deg=0.0,
                        translation_noise_m=0.0, reach_m=0.15, turn_deg=60.0,
                        start_ns=DEFAULT_START_NS, period_ns=2 * NS_PER_S):
    """
    Return n still samples of `cell` from a robot that cannot turn its link freely.

    scara: the link turns about the base z axis only (by up to +-turn_deg from home) and moves
    within +-reach_m of home: the link orientation is Rz(theta) times home's, so every motion
    turns the link about one fixed axis (home's z axis seen in the link frame). gantry: the
    link keeps home's orientation and only moves. Sensor poses get add_pose_noise.
    """
    positions, quaternions = reduced_dof_poses(rng, cell, n, kind, reach_m, turn_deg)
    sensor_p, sensor_q = cell.sensor_poses(positions, quaternions)
    sensor_p, sensor_q = add_pose_noise(rng, sensor_p, sensor_q, rotation_noise_deg,
                                        translation_noise_m)
    return [Sample(start_ns + k * period_ns, Pose(positions[k], quaternions[k]),
                   Pose(sensor_p[k], sensor_q[k])) for k in range(n)]
