"""
ROS 2 node `sim_cell`: a simulated hand-eye cell whose answer is known.

A robot stops at random poses and moves between them (simulation.StopAndGo); the node
publishes, with stamps from its own clock (so use_sim_time works):

- `link_pose` (geometry_msgs/PoseStamped): T_base_link, frame_id = base_frame, at link_rate_hz;
- `sensor_pose` (PoseStamped): T_sensor_obj, frame_id = sensor_frame, as a camera would
  (simulation.SensorModel): sensor_rate_hz, noise, header stamp = exposure time (plus
  clock_offset_s: a sensor clock that leads the robot's), published latency_s after the
  exposure, frames dropped with drop_probability, marker flips with outlier_fraction;
- `~/ground_truth` (TransformStamped, reliable + transient local, depth 1): the mounting,
  link_frame -> sensor_frame (eye_in_hand) or base_frame -> sensor_frame (eye_to_hand),
  stamped with the start of the trajectory (link sample 0).  It is also logged at start.

With tf_mode:=true it publishes like a real cell instead of the two pose topics: the robot as
a chain of two joints on /tf (base_frame -> shoulder -> link_frame, one TFMessage per link
sample, as robot_state_publisher does), the camera driver's static camera_link ->
sensor_frame on /tf_static, and the detector's sensor_frame -> marker_frame on /tf at the
camera's rate, with the same noise, latency and drops. The calibrator reads it with
robot_base_frame, robot_effector_frame, tracking_base_frame and tracking_marker_frame.

With camera_images:=true the sensor is a camera instead (either mode): it publishes `image`
(sensor_msgs/Image, mono8) and `camera_info` of the board in board_file (sensor-data QoS, as a
camera driver does), rendered at the true pose T_sensor_obj (the board's centre at the
object, facing the camera) with the pixel noise and blur of a real image (vision.render),
with the same rate, latency, clock offset and drops; rotation_noise_deg, translation_noise_m
and outlier_fraction do not apply (the calibrator's detector finds the noise in the corners).
The stops then keep the board within IMAGE_VIEW_ANGLE_DEG of the optical axis, at most
IMAGE_INCIDENCE_DEG oblique, so that its corners stay in the image.

link_rotation_noise_deg and link_translation_noise_m put the robot's reported pose off at
each stop by an error of its own (repeatable, as a kinematic error; blended along the moves),
while the sensor sees the true pose.

With robot:=scara the link turns about base z only (by up to rotation_spread_deg), with
robot:=gantry not at all: the calibrator then solves what such motions determine and names the
rest (its "unobservable" output). With seed S, the poses are those of
simulation.stop_and_go_streams() for the same rng, cell
and start: rng = default_rng(S); cell = random_cell(rng, setup[, mounting]); streams(rng, ...).
"""

from dataclasses import dataclass

from geometry_msgs.msg import PoseStamped, TransformStamped
import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import ns_from_s, NS_PER_S, SETUPS
from quatcal_ros.ros import command_line, conversions, spin
from quatcal_ros.ros.qos import LATCHED_QOS, TF_QOS, TF_STATIC_BROADCAST_QOS
from quatcal_ros.sim import simulation
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile
from sensor_msgs.msg import CameraInfo, Image
from tf2_msgs.msg import TFMessage

NODE_NAME = 'sim_cell'
# A clock step larger than this (or backwards) pauses the motion instead of replaying it.
MAX_CLOCK_STEP_NS = 2 * NS_PER_S
STREAM_QOS_DEPTH = 100

# name: (default, description, (min, max) or None); read once at start (read-only).
PARAMETERS = {
    'seed': (0, 'seed of the random cell, stops, noise and drops', (0, 2 ** 31 - 1)),
    'setup': ('eye_in_hand', "'eye_in_hand' (sensor on the link) or 'eye_to_hand' "
              '(sensor fixed in the cell, object on the link)', None),
    'link_rate_hz': (500.0, 'rate of link_pose (Hz)', (1.0, 2000.0)),
    'sensor_rate_hz': (30.0, 'rate of sensor exposures (Hz)', (0.1, 1000.0)),
    'rotation_noise_deg': (0.2, 'sensor rotation noise, std per axis (deg)', (0.0, 10.0)),
    'translation_noise_m': (0.001, 'sensor translation noise, std per axis (m)', (0.0, 0.1)),
    'latency_s': (0.03, 'delay from exposure (header stamp) to publication (s)', (0.0, 2.0)),
    'clock_offset_s': (0.0, "the sensor clock's lead over the robot's: added to every sensor "
                       'stamp (s); the calibrator corrects it with sensor_time_offset_s',
                       (-1.0, 1.0)),
    'drop_probability': (0.05, 'probability that a sensor frame is dropped', (0.0, 1.0)),
    'outlier_fraction': (0.0, 'probability that a frame is a marker flip', (0.0, 1.0)),
    'link_rotation_noise_deg': (0.0, "the robot's reported link pose error at each stop "
                                '(repeatable, as a kinematic error): rotation, std per axis '
                                '(deg)', (0.0, 10.0)),
    'link_translation_noise_m': (0.0, "the robot's reported link pose error at each stop: "
                                 'translation, std per axis (m)', (0.0, 0.1)),
    'still_s': (1.5, 'time the robot stands still at each stop (s)', (0.0, 60.0)),
    'move_s': (2.0, 'time of each move between stops (s)', (0.1, 60.0)),
    'rotation_spread_deg': (30.0, 'largest rotation of a stop from home (deg)', (0.0, 90.0)),
    'robot': ('arm', "'arm' (turns the link about any axis), 'scara' (about base z only) or "
              "'gantry' (never turns)", None),
    'n_stops': (0, 'number of stops, then hold the last one; 0 = forever', (0, 1_000_000)),
    'mounting_xyz': (Parameter.Type.DOUBLE_ARRAY,
                     'mounting translation x, y, z (m); empty = random from seed', None),
    'mounting_rpy_deg': (Parameter.Type.DOUBLE_ARRAY,
                         'mounting roll, pitch, yaw (deg, R = Rz Ry Rx); empty = random', None),
    'base_frame': ('base_link', 'frame_id of link_pose (robot base)', None),
    'link_frame': ('tool0', 'the link the sensor is mounted on (eye_in_hand)', None),
    'sensor_frame': ('camera', 'frame_id of sensor_pose', None),
    'tf_mode': (False, 'publish /tf and /tf_static like a real cell (a two-joint robot, a static '
                'camera_link -> sensor_frame, the marker) instead of link_pose and sensor_pose',
                None),
    'marker_frame': ('marker', 'the observed marker frame (tf_mode)', None),
    'camera_images': (False, 'publish camera images of the board in board_file (image, '
                      'camera_info) instead of the sensor pose: for the calibrator with '
                      'sensor_input:=image', None),
    'board_file': ('', 'the board camera_images draws (board.yaml; the calibrator reads the '
                   'same file)', None),
}
# camera_images: the camera, how far off its axis and how obliquely a stop may show the board
# (its corners then stay in the image), and an image's noise (grey levels) and blur (px).
CAMERA_SIZE = (640, 480)
CAMERA_MATRIX = [[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]
IMAGE_VIEW_ANGLE_DEG = 20.0
IMAGE_INCIDENCE_DEG = 50.0
IMAGE_NOISE = 2.0
IMAGE_BLUR_PX = 0.6
# tf_mode: the camera driver's static transform to the sensor frame (an optical frame: z
# forward, x right, y down), and the first joint.
CAMERA_LINK = 'camera_link'
CAMERA_LINK_TO_SENSOR = Pose.create([0.0, 0.015, 0.0],
                                    quat.from_rotation_vector([-1.2092, 1.2092, -1.2092]))
SHOULDER = 'shoulder'


def shoulder_pose(stamp_ns):
    """Return base -> shoulder at stamp_ns: a joint turning about base z (tf_mode)."""
    return Pose.create([0.0, 0.0, 0.3],
                       quat.from_axis_angle([0.0, 0.0, 1.0], 0.3 * np.sin(stamp_ns * 1e-9)))


@dataclass(frozen=True)
class SimCellConfig:
    """The node's parameters, checked, as plain numbers."""

    seed: int
    setup: str
    link_rate_hz: float
    sensor_rate_hz: float
    rotation_noise_deg: float
    translation_noise_m: float
    latency_s: float
    clock_offset_s: float
    drop_probability: float
    outlier_fraction: float
    link_rotation_noise_deg: float
    link_translation_noise_m: float
    still_s: float
    move_s: float
    rotation_spread_deg: float
    robot: str
    n_stops: int
    mounting: object    # Pose, or None for a random one
    base_frame: str
    link_frame: str
    sensor_frame: str
    tf_mode: bool
    marker_frame: str
    camera_images: bool
    board_file: str


def _descriptor(description, limits):
    descriptor = ParameterDescriptor(description=description, read_only=True)
    if limits is not None:
        low, high = limits
        if isinstance(low, int):
            descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=low, to_value=high)]
    return descriptor


def mounting_from_parameters(xyz, rpy_deg):
    """Mounting Pose from the two array parameters; None when both are empty (random)."""
    xyz, rpy_deg = list(xyz or []), list(rpy_deg or [])
    if not xyz and not rpy_deg:
        return None
    if len(xyz) != 3 or len(rpy_deg) != 3 or not np.all(np.isfinite(xyz + rpy_deg)):
        raise ValueError(
            f'mounting_xyz {xyz} and mounting_rpy_deg {rpy_deg}: give both, 3 finite numbers '
            'each (metres; degrees), or leave both empty for a random mounting')
    roll, pitch, yaw = np.radians(rpy_deg)
    return Pose.create(xyz, simulation.quaternion_wxyz_from_rpy(roll, pitch, yaw))


def read_config(node):
    """Declare the node's parameters (PARAMETERS) and return them as a SimCellConfig."""
    command_line.accept_integers_for_reals(node, {
        name: Parameter.Type.DOUBLE if type(default) is float else default
        for name, (default, _, _) in PARAMETERS.items()
        if type(default) is float or default == Parameter.Type.DOUBLE_ARRAY})
    values = {}
    for name, (default, description, limits) in PARAMETERS.items():
        values[name] = command_line.declared(node, name, default,
                                             _descriptor(description, limits), limits)
    command_line.refuse_unknown_parameters(node, PARAMETERS, NODE_NAME, ValueError)
    if values['robot'] not in simulation.ROBOTS:
        raise ValueError(f'parameter robot must be one of {", ".join(simulation.ROBOTS)}, '
                         f'not {values["robot"]!r}')
    if values['setup'] not in SETUPS:
        setup = values['setup']
        raise ValueError(f'parameter setup must be one of {", ".join(SETUPS)}, not {setup!r}')
    values['mounting'] = mounting_from_parameters(values.pop('mounting_xyz'),
                                                  values.pop('mounting_rpy_deg'))
    if values['camera_images'] and not values['board_file']:
        raise ValueError('camera_images needs board_file: the board to draw (e.g. '
                         'config/sim_board.yaml; give the calibrator the same file)')
    return SimCellConfig(**values)


class SimCamera:
    """The camera of camera_images: renders the board at a pose T_sensor_obj."""

    def __init__(self, board_file, seed):
        from quatcal_ros.vision.board import read_board   # cv2 only with camera_images
        from quatcal_ros.vision.camera import camera_from
        from quatcal_ros.vision.render import Renderer
        self.camera = camera_from(*CAMERA_SIZE, CAMERA_MATRIX, 'plumb_bob', [0.0] * 5)
        self.renderer = Renderer(read_board(board_file), self.camera)
        # The object frame faces the camera (z towards it); the board's z faces away, its
        # origin at a corner: T_obj_board turns it half a turn about x, centred.
        width_m, height_m = self.renderer.board.extent_m
        turn = quat.multiply(quat.from_rotation_vector([np.pi, 0.0, 0.0]),
                             self.renderer.facing)
        self.object_to_board = Pose(
            -quat.matrix_from_quaternion(turn) @ [width_m / 2, height_m / 2, 0.0], turn)
        self._rng = np.random.default_rng([seed, 1])   # (the cell's own draws stay as they were)

    def messages(self, seen, stamp_ns, frame_id):
        """Return the Image (mono8) and the CameraInfo of the board at T_sensor_obj `seen`."""
        gray = self.renderer.render(seen @ self.object_to_board, self._rng, IMAGE_NOISE,
                                    IMAGE_BLUR_PX)
        info = conversions.camera_info_msg(self.camera, stamp_ns, frame_id)
        return conversions.image_msg(gray, info.header), info


def _due_times(next_index, until_ns, rate_hz):
    """Return the grid times (ns) from sample `next_index` up to until_ns, or None if none."""
    last = simulation.last_grid_index(until_ns, rate_hz)
    if last < next_index:
        return None
    return simulation.grid_times_ns(np.arange(next_index, last + 1), rate_hz)


class SimCell(Node):
    """Publishes link and sensor poses of a simulated cell, and its ground truth."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self.config = config = read_config(self)
        rng = np.random.default_rng(config.seed)
        self.cell = simulation.random_cell(rng, config.setup, mounting=config.mounting)
        self.camera = (SimCamera(config.board_file, config.seed) if config.camera_images
                       else None)
        view = ({'max_view_angle_deg': IMAGE_VIEW_ANGLE_DEG,
                 'max_incidence_deg': IMAGE_INCIDENCE_DEG} if self.camera else {})
        self._trajectory = simulation.StopAndGo(
            rng, self.cell, config.still_s, config.move_s, config.n_stops,
            config.rotation_spread_deg, config.robot, **view)
        self._sensor = simulation.SensorModel(
            rng, config.rotation_noise_deg, config.translation_noise_m,
            config.drop_probability, config.outlier_fraction)
        self._latency_ns = ns_from_s(config.latency_s)
        self._clock_offset_ns = ns_from_s(config.clock_offset_s)
        stream_qos = QoSProfile(depth=STREAM_QOS_DEPTH)
        if config.tf_mode:
            self._tf_pub = self.create_publisher(TFMessage, '/tf', TF_QOS)
            self._tf_static_pub = self.create_publisher(
                TFMessage, '/tf_static', TF_STATIC_BROADCAST_QOS)
        else:
            self._link_pub = self.create_publisher(PoseStamped, 'link_pose', stream_qos)
        if self.camera:
            self._image_pub = self.create_publisher(Image, 'image', qos_profile_sensor_data)
            self._info_pub = self.create_publisher(CameraInfo, 'camera_info',
                                                   qos_profile_sensor_data)
        elif not config.tf_mode:
            self._sensor_pub = self.create_publisher(PoseStamped, 'sensor_pose', stream_qos)
        self._truth_pub = self.create_publisher(TransformStamped, '~/ground_truth', LATCHED_QOS)
        self._origin_ns = None      # clock time of trajectory time 0
        self._last_now_ns = None
        self._next_link = 0         # index of the next link sample to publish
        self._next_frame = 0        # index of the next sensor exposure to publish
        self._finished = False
        self._log_truth()
        period_s = 1.0 / max(config.link_rate_hz, config.sensor_rate_hz)
        self._timer = self.create_timer(period_s, self._on_tick)

    @property
    def truth_frames(self):
        """(parent, child) frame ids of the ground truth transform."""
        parent = (self.config.link_frame if self.config.setup == 'eye_in_hand'
                  else self.config.base_frame)
        return parent, self.config.sensor_frame

    def _log_truth(self):
        parent, child = self.truth_frames
        x, y, z, w = quat.xyzw_from_wxyz(self.cell.mounting.quaternion)
        tx, ty, tz = self.cell.mounting.position
        self.get_logger().info(
            f'ground truth {self.config.setup} {parent} -> {child}: quaternion (x, y, z, w) = '
            f'({x:.6f}, {y:.6f}, {z:.6f}, {w:.6f}), translation = ({tx:.4f}, {ty:.4f}, '
            f'{tz:.4f}) m; seed {self.config.seed}')

    def _start(self, now_ns):
        self._origin_ns = now_ns
        parent, child = self.truth_frames
        self._truth_pub.publish(conversions.transform_stamped_msg(
            self.cell.mounting, now_ns, parent, child))
        if self.config.tf_mode:
            self._tf_static_pub.publish(TFMessage(transforms=[conversions.transform_stamped_msg(
                CAMERA_LINK_TO_SENSOR, now_ns, CAMERA_LINK, self.config.sensor_frame)]))

    def _on_tick(self):
        now_ns = self.get_clock().now().nanoseconds
        if now_ns <= 0:
            return   # ROS time not started (use_sim_time before the first /clock)
        if self._origin_ns is None:
            self._start(now_ns)
        elif not 0 <= now_ns - self._last_now_ns <= MAX_CLOCK_STEP_NS:
            step = now_ns - self._last_now_ns
            self._origin_ns += step
            self.get_logger().warning(
                f'clock jumped by {step / 1e9:.3f} s; the robot continues from where it was')
        self._last_now_ns = now_ns
        t_ns = now_ns - self._origin_ns
        self._publish_link(t_ns)
        self._publish_frames(t_ns - self._latency_ns)
        self._check_finished(t_ns)

    def _publish_link(self, t_ns):
        """Publish every link sample due at trajectory time t_ns (all of them if behind)."""
        times = _due_times(self._next_link, t_ns, self.config.link_rate_hz)
        if times is None:
            return
        self._next_link += len(times)
        positions, quaternions = self._reported(times, *self._trajectory.link_poses(times))
        config = self.config
        for t, p, q in zip(times.tolist(), positions, quaternions):
            stamp, link = self._origin_ns + t, Pose(p, q)
            if not config.tf_mode:
                self._link_pub.publish(conversions.pose_stamped_msg(
                    link, stamp, config.base_frame))
                continue
            first = shoulder_pose(stamp)
            self._tf_pub.publish(TFMessage(transforms=[
                conversions.transform_stamped_msg(first, stamp, config.base_frame, SHOULDER),
                conversions.transform_stamped_msg(first.inverse() @ link, stamp, SHOULDER,
                                                  config.link_frame)]))

    def _reported(self, times, positions, quaternions):
        """
        Return the link poses as the robot reports them at `times` (trajectory ns).

        Each stop's pose is off by its own error (a rotation vector on the left and a shift,
        std per axis link_rotation_noise_deg and link_translation_noise_m, drawn from the seed
        and the stop alone), the same every time the robot stands there; along a move the
        error passes from one stop's to the next's.
        The sensor sees the true poses.
        """
        config = self.config
        if not (config.link_rotation_noise_deg or config.link_translation_noise_m):
            return positions, quaternions
        k, following, s = self._trajectory.segments(times)
        stops = np.union1d(k, following)
        errors = np.array([self._stop_error(int(stop)) for stop in stops])   # (stops, 6)
        fraction = s[:, None]
        error = ((1.0 - fraction) * errors[np.searchsorted(stops, k)]
                 + fraction * errors[np.searchsorted(stops, following)])
        return (positions + error[:, 3:], quat.normalize(
            quat.multiply(quat.from_rotation_vector(error[:, :3]), quaternions)))

    def _stop_error(self, stop):
        """Return stop `stop`'s reported pose error: a rotation vector (rad), a shift (m)."""
        z = np.random.default_rng([self.config.seed, 2, stop]).standard_normal(6)
        return np.concatenate([z[:3] * np.radians(self.config.link_rotation_noise_deg),
                               z[3:] * self.config.link_translation_noise_m])

    def _publish_frames(self, exposed_before_ns):
        """Publish the frames exposed up to exposed_before_ns (now minus the latency)."""
        times = _due_times(self._next_frame, exposed_before_ns, self.config.sensor_rate_hz)
        if times is None:
            return
        self._next_frame += len(times)
        true_p, true_q = self.cell.sensor_poses(*self._trajectory.link_poses(times))
        positions, quaternions, kept, _ = self._sensor.observe(true_p, true_q)
        if self.camera:   # the image's pixels carry the noise
            positions, quaternions = true_p, true_q
        config = self.config
        for t, p, q in zip(times[kept].tolist(), positions[kept], quaternions[kept]):
            stamp, seen = self._origin_ns + t + self._clock_offset_ns, Pose(p, q)
            if self.camera:
                image, info = self.camera.messages(seen, stamp, config.sensor_frame)
                self._info_pub.publish(info)
                self._image_pub.publish(image)
            elif config.tf_mode:
                self._tf_pub.publish(TFMessage(transforms=[conversions.transform_stamped_msg(
                    seen, stamp, config.sensor_frame, config.marker_frame)]))
            else:
                self._sensor_pub.publish(conversions.pose_stamped_msg(
                    seen, stamp, config.sensor_frame))

    def _check_finished(self, t_ns):
        duration = self._trajectory.duration_ns
        if not self._finished and duration is not None and t_ns >= duration:
            self._finished = True
            self.get_logger().info(
                f'visited all {self.config.n_stops} stops; holding the last pose')


def command_line_problem(arguments):
    """Return (exit status, text) for --help or a command line sim_cell must not start with."""
    def help_text():
        return command_line.help_text(
            NODE_NAME, 'A simulated hand-eye cell whose answer is known (its ~/ground_truth): '
            'link_pose and sensor_pose, or /tf and /tf_static with tf_mode:=true.',
            [(name, '[]' if isinstance(default, Parameter.Type) else default, text)
             for name, (default, text, _) in PARAMETERS.items()])
    return command_line.problem(arguments, help_text, PARAMETERS)


def main(args=None):
    """Run the sim_cell node until SIGINT or SIGTERM (exit 0); 2 on bad parameters."""
    return spin.run(SimCell, NODE_NAME, (ValueError, ParameterException), 'bad parameters',
                    args, command_line_problem)


if __name__ == '__main__':
    raise SystemExit(main())
