"""
Conversions between geometry_msgs messages and the core's plain numbers.

The only module that reads or writes geometry_msgs fields.  Messages hold quaternions as
(x, y, z, w); the core as (w, x, y, z): fields are read and written by name, never by position.
Times are integer nanoseconds (header stamps).

Reading is duck-typed, so the message classes of rclpy (geometry_msgs.msg) and those of the
pure-Python `rosbags` library (same field names) work alike.  Builders import geometry_msgs
only when called, or build rosbags classes from a typestore, so this module also imports where
only rosbags is installed.
"""

import math
from operator import attrgetter

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import covariance_problem, Pose
from quatcal_ros.core.units import MESSAGE_NORM_TOLERANCE, NS_PER_S
from quatcal_ros.stream.tf_tree import normalize_frame

# A quaternion with a smaller norm is a zero quaternion (reason 'zero_quaternion').
ZERO_NORM = 1e-6
_INT32_MIN, _INT32_MAX = -2 ** 31, 2 ** 31 - 1


class BadPoseError(ValueError):
    """
    A pose holds numbers that are not a pose; the message names the field.

    `field` is the offending field ('pose.position.x', 'pose.orientation', ...); `reason`
    one of 'non_finite', 'zero_quaternion', 'non_unit_quaternion', 'bad_covariance',
    'malformed' (the codes of message_checks.REASONS).
    """

    def __init__(self, message, field='', reason='malformed'):
        super().__init__(message)
        self.field = field
        self.reason = reason


# --- reading ---------------------------------------------------------------------------------

def _number(value, name):
    try:
        return float(value)
    except (TypeError, ValueError):
        raise BadPoseError(f'{name} is not a number ({value!r})', name) from None


def validate_pose_numbers(position, quaternion_xyzw, norm_tolerance=MESSAGE_NORM_TOLERANCE,
                          position_name='position', orientation_name='orientation'):
    """
    Check a position (3,) and a quaternion (x, y, z, w); return them as arrays, unit q.

    Raises BadPoseError naming the field: a NaN or infinite component ('position.x is nan'),
    or a quaternion whose norm is farther than norm_tolerance from 1 ('orientation has norm
    0.00').  A quaternion within the tolerance is renormalised.
    """
    if norm_tolerance < 0.0:
        raise ValueError(f'norm_tolerance must be >= 0, not {norm_tolerance}')
    # Fast path (every message of a live stream): plain floats, no names formatted.
    try:
        px, py, pz = position
        qx, qy, qz, qw = quaternion_xyzw
        values = (float(px), float(py), float(pz), float(qx), float(qy), float(qz), float(qw))
    except (TypeError, ValueError):
        values = None
    if values is not None and math.isfinite(sum(values)):
        norm = math.hypot(*values[3:])
        if abs(norm - 1.0) <= norm_tolerance:
            return np.array(values[:3]), np.array(values[3:]) / norm
    return _validate_slowly(position, quaternion_xyzw, norm_tolerance, position_name,
                            orientation_name)


def _validate_slowly(position, quaternion_xyzw, norm_tolerance, position_name,
                     orientation_name):
    """validate_pose_numbers field by field, raising BadPoseError with the field's name."""
    position, quaternion_xyzw = list(position), list(quaternion_xyzw)
    if len(position) != 3 or len(quaternion_xyzw) != 4:
        raise BadPoseError(f'expected 3 position and 4 quaternion components, got '
                           f'{len(position)} and {len(quaternion_xyzw)}')
    fields = ([(f'{position_name}.{axis}', v) for axis, v in zip('xyz', position)]
              + [(f'{orientation_name}.{axis}', v) for axis, v in zip('xyzw', quaternion_xyzw)])
    values = [_number(v, name) for name, v in fields]
    for (name, _), v in zip(fields, values):
        if not math.isfinite(v):
            raise BadPoseError(f'{name} is {v}', name, 'non_finite')
    q = np.array(values[3:])
    norm = math.hypot(*values[3:])   # no overflow for huge components
    if abs(norm - 1.0) > norm_tolerance:
        shown = (f'{norm:.6f}' if abs(norm - 1.0) < 0.01 else f'{norm:.2f}' if norm < 1e3
                 else f'{norm:.3g}')   # (a component of 1e200 printed 200 digits)
        raise BadPoseError(
            f'{orientation_name} has norm {shown}; a rotation quaternion has norm 1 '
            f'(accepted within {norm_tolerance:g})', orientation_name,
            'zero_quaternion' if norm < ZERO_NORM else 'non_unit_quaternion')
    return np.array(values[:3]), q / norm


def _pose_fields(msg):
    """(position, orientation, their names) of a Pose/PoseStamped/Transform(Stamped)-like msg."""
    obj, path = msg, ''
    while hasattr(obj, 'pose'):   # PoseStamped, PoseWithCovariance(Stamped), Odometry
        obj, path = obj.pose, path + 'pose.'
    if hasattr(obj, 'transform'):
        obj, path = obj.transform, path + 'transform.'
    for linear, angular in (('position', 'orientation'), ('translation', 'rotation')):
        if hasattr(obj, linear) and hasattr(obj, angular):
            return (getattr(obj, linear), getattr(obj, angular),
                    path + linear, path + angular)
    raise TypeError(f'expected a geometry_msgs Pose, PoseStamped, Transform or '
                    f'TransformStamped, got {type(msg).__name__}')


_LAYOUTS = {}   # message class -> getters of its position and orientation, their names


def pose_from_msg(msg, norm_tolerance=MESSAGE_NORM_TOLERANCE):
    """
    Pose (quaternion (w, x, y, z)) of a geometry_msgs Pose, PoseStamped, Transform, ...

    Duck-typed: anything with .pose (descended repeatedly) or .transform, holding
    position/orientation or translation/rotation with x, y, z (, w) fields.  Raises
    BadPoseError naming the field for NaN, inf or a non-unit quaternion (validate_pose_numbers).
    """
    layout = _LAYOUTS.get(type(msg))
    if layout is None:   # found once per message class
        _, _, position_name, orientation_name = _pose_fields(msg)
        covariance_name = _covariance_field(msg)
        layout = _LAYOUTS[type(msg)] = (attrgetter(position_name), attrgetter(orientation_name),
                                        position_name, orientation_name,
                                        covariance_name and attrgetter(covariance_name))
    get_position, get_orientation, position_name, orientation_name, get_covariance = layout
    if get_covariance is not None:   # PoseWithCovariance(Stamped)
        pose = _pose_numbers(msg, layout, norm_tolerance)
        return Pose(pose.position, pose.quaternion, covariance_from_msg(get_covariance(msg)))
    return _pose_numbers(msg, layout, norm_tolerance)


def _covariance_field(msg):
    """Return the name of a PoseWithCovariance(Stamped)'s covariance field, or None."""
    obj, path = msg, ''
    while hasattr(obj, 'pose'):
        if hasattr(obj, 'covariance'):
            return path + 'covariance'
        obj, path = obj.pose, path + 'pose.'
    return None


def covariance_from_msg(values):
    """
    Return a PoseWithCovariance's 36 values as a 6x6 (ROS order), or None when unknown.

    Zero is what drivers publish when they do not know the covariance: all of it, or the
    rotation's or the position's rows and columns alone (a driver that knows only the
    other part, usable itself; every such message had been dropped as bad): None, the pose
    is used unweighted. Raises BadPoseError (reason 'bad_covariance') when the matrix is not usable
    (pose.covariance_problem).
    """
    covariance = np.asarray(values, dtype=float).reshape(6, 6)
    position, rotation = covariance[:3, :3], covariance[3:, 3:]   # ROS order: position first
    if not (position.any() and rotation.any()) and not (
            covariance[:3, 3:].any() or covariance[3:, :3].any()):
        given = position if position.any() else rotation   # zero too: all zero, unknown
        problem = covariance_problem(given) if given.any() else None
        if problem is None:
            return None
    else:
        problem = covariance_problem(covariance)
    if problem:
        raise BadPoseError(f'pose.covariance: {problem}', 'pose.covariance', 'bad_covariance')
    return covariance


def _pose_numbers(msg, layout, norm_tolerance):
    get_position, get_orientation, position_name, orientation_name, _ = layout
    position, orientation = get_position(msg), get_orientation(msg)
    # Fast path: plain floats through pose_from_values (the raw decoders' arithmetic), which
    # builds (w, x, y, z) directly; what it refuses, validate_pose_numbers names.
    try:
        x, y, z = float(position.x), float(position.y), float(position.z)
        qx, qy = float(orientation.x), float(orientation.y)
        qz, qw = float(orientation.z), float(orientation.w)
    except (TypeError, ValueError):
        x = math.nan   # not numbers: validate_pose_numbers names the field
    else:
        pose = pose_from_values(x, y, z, qx, qy, qz, qw, norm_tolerance)
        if pose is not None:
            return pose
    p, q_xyzw = validate_pose_numbers(
        (position.x, position.y, position.z),
        (orientation.x, orientation.y, orientation.z, orientation.w),
        norm_tolerance, position_name, orientation_name)
    return Pose(p, quat.wxyz_from_xyzw(q_xyzw))


def pose_from_values(x, y, z, qx, qy, qz, qw, norm_tolerance=MESSAGE_NORM_TOLERANCE):
    """
    Return the Pose of a message's seven floats (position, quaternion x, y, z, w), or None.

    None when a number is NaN or infinite or the quaternion's norm is off by more than
    norm_tolerance: pose_from_msg then names the field. Within it the quaternion is divided
    by its norm (the arithmetic every decoder of pose messages shares, bit for bit).
    """
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if math.isfinite(x + y + z) and abs(norm - 1.0) <= norm_tolerance:   # NaN fails
        return Pose(np.array((x, y, z)), np.array((qw / norm, qx / norm, qy / norm, qz / norm)))
    return None


def frame_ids(msg):
    """Return (header.frame_id, child_frame_id or None) of a stamped message, without '/'."""
    child = getattr(msg, 'child_frame_id', None)
    return normalize_frame(msg.header.frame_id), None if child is None else normalize_frame(child)


def stamp_ns_from_header(header):
    """Integer nanoseconds of a std_msgs/Header (or a builtin_interfaces/Time) stamp."""
    stamp = getattr(header, 'stamp', header)
    nanosec = int(stamp.nanosec)
    if not 0 <= nanosec < NS_PER_S:
        raise ValueError(f'stamp.nanosec must be in [0, 1e9), not {nanosec}')
    return int(stamp.sec) * NS_PER_S + nanosec


# --- building --------------------------------------------------------------------------------

def _msg_class(name, typestore):
    """Message class 'pkg/msg/Name': from rclpy's Python packages, or a rosbags typestore."""
    if typestore is not None:
        return typestore.types[name]
    package, _, type_name = name.split('/')
    if package == 'geometry_msgs':
        import geometry_msgs.msg as module
    elif package == 'std_msgs':
        import std_msgs.msg as module
    else:
        import builtin_interfaces.msg as module
    return getattr(module, type_name)


def time_msg(stamp_ns, typestore=None):
    """builtin_interfaces/Time of integer nanoseconds (sec may be negative, nanosec >= 0)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise ValueError(f'stamp {stamp_ns} ns does not fit builtin_interfaces/Time (int32 sec)')
    return _msg_class('builtin_interfaces/msg/Time', typestore)(sec=sec, nanosec=nanosec)


def _header(stamp_ns, frame_id, typestore):
    return _msg_class('std_msgs/msg/Header', typestore)(
        stamp=time_msg(stamp_ns, typestore), frame_id=str(frame_id))


def _quaternion_msg(q_wxyz, typestore):
    w, x, y, z = (float(v) for v in quat.normalize(q_wxyz))
    return _msg_class('geometry_msgs/msg/Quaternion', typestore)(x=x, y=y, z=z, w=w)


def _vector(cls_name, position, typestore):
    x, y, z = (float(v) for v in position)
    return _msg_class(cls_name, typestore)(x=x, y=y, z=z)


def pose_msg(pose, typestore=None):
    """geometry_msgs/Pose of a Pose."""
    return _msg_class('geometry_msgs/msg/Pose', typestore)(
        position=_vector('geometry_msgs/msg/Point', pose.position, typestore),
        orientation=_quaternion_msg(pose.quaternion, typestore))


def pose_stamped_msg(pose, stamp_ns, frame_id, typestore=None):
    """geometry_msgs/PoseStamped of a Pose (typestore: build rosbags classes instead)."""
    return _msg_class('geometry_msgs/msg/PoseStamped', typestore)(
        header=_header(stamp_ns, frame_id, typestore), pose=pose_msg(pose, typestore))


def pose_with_covariance_stamped_msg(pose, stamp_ns, frame_id, typestore=None):
    """geometry_msgs/PoseWithCovarianceStamped of a Pose and its covariance (zeros: none)."""
    covariance = np.zeros(36) if pose.covariance is None else np.ravel(pose.covariance)
    with_covariance = _msg_class('geometry_msgs/msg/PoseWithCovariance', typestore)(
        pose=pose_msg(pose, typestore),
        covariance=(covariance.astype(float) if typestore is not None
                    else [float(v) for v in covariance]))
    return _msg_class('geometry_msgs/msg/PoseWithCovarianceStamped', typestore)(
        header=_header(stamp_ns, frame_id, typestore), pose=with_covariance)


def transform_stamped_msg(pose, stamp_ns, frame_id, child_frame_id, typestore=None):
    """geometry_msgs/TransformStamped of a Pose T_frame_child."""
    transform = _msg_class('geometry_msgs/msg/Transform', typestore)(
        translation=_vector('geometry_msgs/msg/Vector3', pose.position, typestore),
        rotation=_quaternion_msg(pose.quaternion, typestore))
    return _msg_class('geometry_msgs/msg/TransformStamped', typestore)(
        header=_header(stamp_ns, frame_id, typestore), child_frame_id=str(child_frame_id),
        transform=transform)


def quaternion_stamped_msg(q_wxyz, stamp_ns, frame_id, typestore=None):
    """geometry_msgs/QuaternionStamped of a quaternion (w, x, y, z), normalised."""
    return _msg_class('geometry_msgs/msg/QuaternionStamped', typestore)(
        header=_header(stamp_ns, frame_id, typestore),
        quaternion=_quaternion_msg(q_wxyz, typestore))


# --- camera images (the target detector) -----------------------------------------------------

# Image encodings read, with their channels and the OpenCV conversion to grey.
IMAGE_ENCODINGS = {'mono8': (1, None), '8UC1': (1, None), 'mono16': (1, None),
                   '16UC1': (1, None), 'bgr8': (3, 'COLOR_BGR2GRAY'),
                   'rgb8': (3, 'COLOR_RGB2GRAY'), 'bgra8': (4, 'COLOR_BGRA2GRAY'),
                   'rgba8': (4, 'COLOR_RGBA2GRAY'), '8UC3': (3, 'COLOR_BGR2GRAY')}


class BadImageError(ValueError):
    """An image message that is not an image of a known encoding; the message says why."""


def gray_from_image_msg(msg):
    """Return the grayscale uint8 array of a sensor_msgs Image or CompressedImage."""
    import cv2
    from quatcal_ros.vision.image_decode import decode_gray, gray_8bit   # cv2: images only
    if hasattr(msg, 'format'):   # CompressedImage
        gray, why = decode_gray(bytes(msg.data))
        if gray is None:
            raise BadImageError(f'compressed image ({msg.format or "no format"}) does not '
                                f'decode: {why}')
        return gray
    encoding = msg.encoding
    if encoding not in IMAGE_ENCODINGS:
        raise BadImageError(f'encoding {encoding!r} is not one of '
                            f'{", ".join(IMAGE_ENCODINGS)}')
    channels, conversion = IMAGE_ENCODINGS[encoding]
    depth = 2 if '16' in encoding else 1
    width, height, step = int(msg.width), int(msg.height), int(msg.step)
    data = bytes(msg.data)
    if not width or not height or step < width * channels * depth \
            or len(data) < step * height:
        raise BadImageError(f'{width}x{height} {encoding} with step {step} and {len(data)} '
                            'bytes of data is not a whole image')
    rows = np.frombuffer(data, np.uint8)[:step * height].reshape(height, step)
    pixels = rows[:, :width * channels * depth]
    if depth == 2:
        return gray_8bit(pixels.view('>u2' if msg.is_bigendian else '<u2').reshape(height,
                                                                                   width))
    if conversion is None:
        return np.ascontiguousarray(pixels)
    return cv2.cvtColor(pixels.reshape(height, width, channels), getattr(cv2, conversion))


def camera_from_camera_info(msg):
    """Return the vision.camera.Camera of a sensor_msgs CameraInfo (BadInputError if not one)."""
    from quatcal_ros.vision.camera import camera_from
    return camera_from(int(msg.width), int(msg.height), np.array(msg.k, dtype=float),
                       msg.distortion_model, np.array(msg.d, dtype=float), 'camera_info')


def camera_info_msg(camera, stamp_ns=0, frame_id=''):
    """Return the sensor_msgs/CameraInfo (rclpy) of a vision.camera.Camera: its inverse."""
    from sensor_msgs.msg import CameraInfo
    return CameraInfo(header=_header(stamp_ns, frame_id, None), width=camera.width,
                      height=camera.height, distortion_model=camera.distortion_model,
                      d=[float(v) for v in camera.D], k=[float(v) for v in camera.K.ravel()],
                      r=[float(v) for v in np.eye(3).ravel()],
                      p=[float(v) for v in np.column_stack([camera.K, np.zeros(3)]).ravel()])


def image_msg(image, header):
    """Return a sensor_msgs/Image of a uint8 array: mono8 (H, W) or bgr8 (H, W, 3)."""
    from sensor_msgs.msg import Image
    height, width = image.shape[:2]
    channels = 1 if image.ndim == 2 else 3
    return Image(header=header, height=height, width=width,
                 encoding='mono8' if channels == 1 else 'bgr8', is_bigendian=0,
                 step=width * channels, data=np.ascontiguousarray(image).tobytes())
