"""
The result in the formats of the ROS ecosystem: easy_handeye2's calibration file and tf2_ros.

- `easy_handeye2_yaml`: the layout that easy_handeye2 (ROS 2) saves and loads as
  ~/.ros2/easy_handeye2/calibrations/NAME.calib, the YAML of its message
  easy_handeye2_msgs/HandeyeCalibration:

      # NAME.calib
      parameters:
        name: NAME
        calibration_type: eye_in_hand        # or eye_on_base (our eye_to_hand)
        robot_base_frame: ..
        robot_effector_frame: ..
        tracking_base_frame: ..              # the sensor (camera) frame: the child frame
        tracking_marker_frame: ..
        freehand_robot_movement: true
        move_group_namespace: /
        move_group: manipulator
      transform:
        translation: {x: .., y: .., z: ..}   # metres
        rotation: {x: .., y: .., z: .., w: ..}

  The transform is T_effector_tracking_base (eye_in_hand) or T_base_tracking_base
  (eye_on_base): our answer, parent frame -> sensor frame.  easy_handeye2 reads the file with
  rosidl_runtime_py.set_message_fields, which refuses keys that are not message fields, so
  the file holds exactly these keys; our quality figures go into YAML comments.
- `static_transform_publisher_command`: the `ros2 run tf2_ros static_transform_publisher`
  line (Jazzy flag syntax) that broadcasts the result on /tf_static.
- `urdf_joint`, `xacro_macro`: the mounting as a fixed URDF joint and as a xacro macro, to
  commit into the robot description (DESIGN.md contract 6: "urdf", "xacro").

Core module: standard library, numpy and PyYAML; no rclpy.  Quaternions in the core are
(w, x, y, z); both outputs use ROS's (x, y, z, w), written field by field.
"""

from html import escape   # &, <, >, both quotes: XML attribute values (and a light import)
import math
from pathlib import Path
import re
import shlex

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.units import DEFAULT_FRAMES
from quatcal_ros.files import plain_yaml

# easy_handeye2's calibration_type for each of our setups.
EASY_HANDEYE2_TYPES = {'eye_in_hand': 'eye_in_hand', 'eye_to_hand': 'eye_on_base'}
SETUPS_BY_EASY_HANDEYE2_TYPE = {value: key for key, value in EASY_HANDEYE2_TYPES.items()}
# Decimals of the numbers on the static_transform_publisher line: 0.1 nm and 1e-10.
COMMAND_DECIMALS = 10


def default_frames(setup):
    """Return (parent, child) frame names used when none are given, for `setup`."""
    try:
        return DEFAULT_FRAMES[setup]
    except KeyError:
        raise ValueError(f'setup must be one of {", ".join(DEFAULT_FRAMES)}, not '
                         f'{setup!r}') from None


def choose_frames(setup, *candidates):
    """
    Return the (parent, child) frames of the result: the first name given of each, in order.

    candidates: (parent, child) pairs, most wanted first (the user's options, then what the
    input names), each name possibly None or ''; default_frames(setup) when none names one.
    """
    chosen = []
    for index, default in enumerate(default_frames(setup)):
        names = [pair[index] for pair in candidates if pair is not None and pair[index]]
        chosen.append(names[0] if names else default)
    return tuple(chosen)


def _translation(result):
    translation = getattr(result, 'translation', None)
    if translation is None:
        raise ValueError('the result has no translation')
    translation = np.asarray(translation, dtype=float).reshape(3)
    if not np.all(np.isfinite(translation)):
        raise ValueError(f'the translation is not finite: {translation}')
    return translation


def _rotation_xyzw(result):
    """
    (x, y, z, w) of the result's unit quaternion (w, x, y, z), w >= 0.

    A quaternion that is unit to rounding is written as it is, so that every output of one
    result (this file, the JSON, the log) shows the same digits.
    """
    q = np.asarray(result.quaternion, dtype=float).reshape(4)
    if abs(np.linalg.norm(q) - 1.0) > 1e-12:
        q = quat.normalize(q)
    if q[0] < 0.0:
        q = -q
    return quat.xyzw_from_wxyz(q)


def easy_handeye2_document(result, parent_frame, child_frame, setup='eye_in_hand', name=None,
                           robot_base_frame='', robot_effector_frame='',
                           tracking_marker_frame='', freehand_robot_movement=True):
    """
    Build the easy_handeye2 calibration document (plain Python types) of a result.

    :param result: a calibration.CalibrationResult (quaternion (w, x, y, z), translation (m)).
    :param parent_frame: the result's parent frame: the robot effector (eye_in_hand) or the
        robot base (eye_to_hand); written as robot_effector_frame or robot_base_frame.
    :param child_frame: the sensor frame, written as tracking_base_frame.
    :param setup: 'eye_in_hand' or 'eye_to_hand' (calibration_type eye_in_hand / eye_on_base).
    :param name: the calibration's name (easy_handeye2 loads NAME.calib); default
        'quatcal_' + setup.
    :param robot_base_frame: the robot base frame for eye_in_hand ('' when unknown).
    :param robot_effector_frame: the robot effector frame for eye_to_hand ('' when unknown).
    :param tracking_marker_frame: the marker (object) frame ('' when unknown).
    :param freehand_robot_movement: easy_handeye2's flag; informational only.
    :return: a dict with 'parameters' and 'transform', as easy_handeye2 writes them.
    :raises ValueError: for an unknown setup or a result without a finite translation.
    """
    calibration_type = EASY_HANDEYE2_TYPES.get(setup)
    if calibration_type is None:
        raise ValueError(f'setup must be one of {", ".join(EASY_HANDEYE2_TYPES)}, not '
                         f'{setup!r}')
    if setup == 'eye_in_hand':
        robot_effector_frame = parent_frame
    else:
        robot_base_frame = parent_frame
    tx, ty, tz = (float(v) for v in _translation(result))
    x, y, z, w = (float(v) for v in _rotation_xyzw(result))
    return {
        'parameters': {
            'name': str(name) if name else f'quatcal_{setup}',
            'calibration_type': calibration_type,
            'robot_base_frame': str(robot_base_frame),
            'robot_effector_frame': str(robot_effector_frame),
            'tracking_base_frame': str(child_frame),
            'tracking_marker_frame': str(tracking_marker_frame),
            'freehand_robot_movement': bool(freehand_robot_movement),
            'move_group_namespace': '/',
            'move_group': 'manipulator',
        },
        'transform': {
            'translation': {'x': tx, 'y': ty, 'z': tz},
            'rotation': {'x': x, 'y': y, 'z': z, 'w': w},
        },
    }


def _figure(value, unit):
    value = None if value is None else float(value)
    return f'{value:.3g} {unit}' if value is not None and math.isfinite(value) else 'unknown'


def easy_handeye2_yaml(result, parent_frame, child_frame, setup='eye_in_hand', name=None,
                       **parameters):
    """
    Return the result as easy_handeye2 calibration file text (see easy_handeye2_document).

    The header comments name the tool and the quality figures; the YAML itself holds only
    the keys of easy_handeye2_msgs/HandeyeCalibration, so easy_handeye2 loads it as it is.
    """
    document = easy_handeye2_document(result, parent_frame, child_frame, setup, name,
                                      **parameters)
    header = (
        '# Hand-eye calibration by quatcal_ros, in the easy_handeye2 calibration layout\n'
        f'# (easy_handeye2_msgs/HandeyeCalibration). transform: {_comment(parent_frame)} -> '
        f'{_comment(child_frame)},\n'
        '# translation in metres, rotation quaternion x, y, z, w.\n'
        f'# method {getattr(result, "method", "") or "unknown"}, '
        f'{getattr(result, "samples", "?")} samples; '
        f'uncertainty {_figure(getattr(result, "uncertainty_deg", None), "deg")} (rotation), '
        f'{_figure(getattr(result, "translation_uncertainty_mm", None), "mm")} '
        '(translation).\n'
        '# easy_handeye2 loads it from ~/.ros2/easy_handeye2/calibrations/NAME.calib, NAME = '
        'parameters.name.\n')
    return header + plain_yaml.dump(document, sort_keys=False, default_flow_style=False)


def _comment(text):
    """
    Return `text` for a YAML comment: each character that is not printable as its escape.

    A line break of any kind (YAML ends a comment at NEL and the Unicode line and paragraph
    separators too) would let the rest of the name become YAML.
    """
    return ''.join(c if c.isprintable() else c.encode('unicode_escape').decode('ascii')
                   for c in str(text))


def easy_handeye2_name(path):
    """Return the calibration name easy_handeye2 gives the file `path` (its stem)."""
    return Path(str(path)).expanduser().stem or 'quatcal'


def _number(value):
    """Text of a float to COMMAND_DECIMALS decimals, trailing zeros dropped; never '-0'."""
    text = f'{float(value):.{COMMAND_DECIMALS}f}'.rstrip('0').rstrip('.')
    return '0' if float(text) == 0.0 else text


def static_transform_publisher_arguments(result, parent_frame, child_frame):
    """
    Return the arguments of tf2_ros static_transform_publisher (Jazzy flags) for a result.

    ['--x', X, '--y', Y, '--z', Z, '--qx', QX, '--qy', QY, '--qz', QZ, '--qw', QW,
     '--frame-id', PARENT, '--child-frame-id', CHILD]: the transform parent -> child, as in a
    launch file's `arguments=`.
    :raises ValueError: for a result without a finite translation.
    """
    values = list(_translation(result)) + list(_rotation_xyzw(result))
    arguments = []
    for flag, value in zip(('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw'), values):
        arguments += [f'--{flag}', _number(value)]
    return arguments + ['--frame-id', str(parent_frame), '--child-frame-id', str(child_frame)]


def static_transform_publisher_command(result, parent_frame, child_frame):
    """
    Return the shell line that broadcasts the result on /tf_static.

    `ros2 run tf2_ros static_transform_publisher --x .. --y .. --z .. --qx .. --qy .. --qz ..
    --qw .. --frame-id PARENT --child-frame-id CHILD` (frame names shell-quoted if needed).
    """
    arguments = static_transform_publisher_arguments(result, parent_frame, child_frame)
    return ' '.join(['ros2', 'run', 'tf2_ros', 'static_transform_publisher']
                    + [shlex.quote(argument) for argument in arguments])


def urdf_rpy(result):
    """
    Return URDF's (roll, pitch, yaw) of the result's rotation, radians.

    URDF's origin rotates by R = Rz(yaw) Ry(pitch) Rx(roll) (fixed axes x, y, z). At
    pitch = +-90 deg roll and yaw are not separable: yaw is then 0 and roll takes it all.
    """
    R = quat.matrix_from_quaternion(np.asarray(result.quaternion, dtype=float).reshape(4))
    pitch = float(np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0])))
    if np.hypot(R[0, 0], R[1, 0]) < 1e-12:   # gimbal lock
        return float(np.arctan2(-R[1, 2], R[1, 1])), pitch, 0.0
    return float(np.arctan2(R[2, 1], R[2, 2])), pitch, float(np.arctan2(R[1, 0], R[0, 0]))


def _joint(result, parent_link, child_frame, indent='', note=''):
    """
    Return the fixed <joint> element of the result; parent_link: the (escaped) link name.

    note: why the joint is not the calibrated frames' (stream.tf_joint), an XML comment above.
    """
    xyz = ' '.join(_number(v) for v in _translation(result))
    rpy = ' '.join(_number(v) for v in urdf_rpy(result))
    comment = [f'<!-- {re.sub(r"-(?=-)", "- ", note)} -->'] if note else []   # (no -- in one)
    lines = [*comment, f'<joint name="{escape(f"{child_frame}_mount_joint")}" type="fixed">',
             f'  <parent link="{parent_link}"/>',
             f'  <child link="{escape(str(child_frame))}"/>',
             f'  <origin xyz="{xyz}" rpy="{rpy}"/>',
             '</joint>']
    return ''.join(f'{indent}{line}\n' for line in lines)


def urdf_joint(result, parent_frame, child_frame, note=''):
    """
    Return the fixed URDF joint parent_frame -> child_frame of the result (text).

    <joint name=".." type="fixed"><parent link=".."/><child link=".."/><origin xyz=".."
    rpy=".."/></joint>, to commit the mounting into a robot description; `note` (why these
    frames) an XML comment above it.
    """
    return _joint(result, escape(str(parent_frame)), child_frame, note=note)


def xacro_macro(result, parent_frame, child_frame, note=''):
    """
    Return the result as a xacro macro (text): the fixed joint, with the parent a parameter.

    <xacro:CHILD_mount parent="PARENT"/> in a robot's xacro adds the joint (the child link
    itself is the sensor driver's or the description's). CHILD is the child frame with each
    character other than an ASCII letter, digit or _ written _ (and a leading digit after
    one), so that it is an XML name and a xacro one: a frame
    such as robot1/camera_link gave an element nobody could write. A ${ or $( in a frame
    name is written $${ or $$(, which xacro reads back as the name, not an expression.
    """
    name = re.sub(r'[^A-Za-z0-9_]', '_', str(child_frame))
    name = f'_{name}' if name[:1].isdigit() else name
    default = _xacro_literal(escape(str(parent_frame)))
    return ('<?xml version="1.0"?>\n'
            '<robot xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
            f'  <xacro:macro name="{name}_mount" params="parent:={default}">\n'
            + _joint(result, '${parent}', _xacro_literal(str(child_frame)), indent='    ',
                     note=_xacro_literal(note))
            + '  </xacro:macro>\n'
            '</robot>\n')


def description_joints(result, parent_frame, child_frame, note=''):
    """
    Return {'urdf': .., 'xacro': ..}: the fixed joint of the result, for a robot description.

    With TF input pass a stream.tf_joint.Joint's fields: the joint a tree can take.
    :raises ValueError: when the result has no (finite) translation.
    """
    return {'urdf': urdf_joint(result, parent_frame, child_frame, note),
            'xacro': xacro_macro(result, parent_frame, child_frame, note)}


def _xacro_literal(text):
    """Return `text` with each ${ and $( escaped (one more $), as xacro reads it back."""
    return re.sub(r'(\$+)(?=[{(])', r'\1$', text)
