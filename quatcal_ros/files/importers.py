"""
Samples saved by other hand-eye tools, read as the core's still samples (pose.Sample).

Formats (each checked against the tool's source):

- easy_handeye2 (ROS 2) `.samples`: the YAML of easy_handeye2_msgs/SampleList, written by its
  handeye_sampler (rosidl_runtime_py.message_to_yaml):

      parameters: {name, calibration_type, robot_base_frame, ...}   # often left empty
      samples:
      - robot:    {translation: {x, y, z}, rotation: {x, y, z, w}}
        tracking: {translation: {x, y, z}, rotation: {x, y, z, w}}

  `tracking` is tf2's lookup_transform(tracking_base_frame, tracking_marker_frame): the marker
  in the sensor frame, T_sensor_obj, our sensor pose.  `robot` is lookup_transform(
  robot_base_frame, robot_effector_frame) = T_base_effector for eye_in_hand, but the inverse,
  lookup_transform(robot_effector_frame, robot_base_frame) = T_effector_base, for eye_on_base
  (easy_handeye2 inverts it so that OpenCV's eye-in-hand solver returns T_base_camera).  Those
  are turned back into T_base_effector here, so the setup must be known: from the file's
  calibration_type when it names one, else from the caller.
- moveit_calibration samples YAML (handeye_control_widget "Save samples"): a list of
  `{effector_wrt_world: [16 numbers], object_wrt_sensor: [16 numbers]}`, each a 4x4
  homogeneous matrix in row-major order: T_base_eef and T_sensor_obj, for both setups.
- moveit_calibration's solver test data (pose_samples.json, data/moveit_pose_samples): a JSON list
  of `[eef_wrt_world, obj_wrt_sensor]` pairs of nested 4x4 row-major matrices.

The files hold no time stamps: sample i gets the stamp i seconds.  YAML is read with
yaml.safe_load only (plain data, never objects).  Errors are text_input.BadInputError naming
the file, the entry and the field, e.g. `cell.samples, entry samples[3], field
robot.rotation.w: 'abc' is not a number`.
"""

from dataclasses import dataclass, field, replace
import math
from pathlib import Path

import numpy as np
from quatcal_ros.core.pose import Pose, Sample
from quatcal_ros.core.quaternion import quaternion_from_matrix, wxyz_from_xyzw, xyz_json, \
    xyzw_json
from quatcal_ros.core.units import FILE_NORM_TOLERANCE, NS_PER_S, plain_number, \
    position_problem, quaternion_norm_problem, shown
from quatcal_ros.files import exports, journal, plain_yaml
from quatcal_ros.files.samples_csv import parse_samples_and_rows
from quatcal_ros.files.text_input import BadInputError, read_text

FORMATS = ('csv', 'easy_handeye2', 'moveit', 'moveit-json')
# A 4x4 matrix whose rotation block is farther than this from orthonormal (max |R^T R - I|)
# is not a pose.
ROTATION_TOLERANCE = 1e-3
SUFFIX_FORMATS = {'.csv': 'csv', '.samples': 'easy_handeye2', '.json': 'moveit-json'}


@dataclass(frozen=True)
class ImportedSamples:
    """
    Samples read from a file, and what the file says about them.

    file_format: one of FORMATS.  setup: the setup the file names (easy_handeye2's
    calibration_type), or None.  frames: frame names the file names, by easy_handeye2
    parameter name ('robot_base_frame', ...), empty ones left out.  warnings: sentences for
    the result's warnings (what the file left open).  invert_sensor: whether to solve the
    sensor poses inverted: the caller's value (load_samples), else a journal header's, or None
    (neither says). static_chain: a journal's TF joint (journal.JournalHeader), or None.
    rows: the file row of each sample (a CSV's, as its errors count them), or None.
    """

    samples: list
    file_format: str
    setup: str = None
    frames: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    invert_sensor: bool = None
    static_chain: tuple = None
    rows: list = None


# --- reading files ---------------------------------------------------------------------------

def _load_yaml(text, name):
    return plain_yaml.load(text, name, holds='a samples file')


def _load_json(text, name):
    return plain_yaml.load_json(text, name)


# --- numbers and poses -----------------------------------------------------------------------

def _number(value, where):
    if isinstance(value, bool) or value is None:
        raise BadInputError(f'{where}: {shown(repr(value))} is not a number')
    try:   # (a YAML or JSON string '0_5' is no number, as a CSV cell of it is not)
        number = plain_number(value) if isinstance(value, str) else float(value)
    except (TypeError, ValueError):
        raise BadInputError(f'{where}: {shown(repr(value))} is not a number') from None
    if not math.isfinite(number):
        raise BadInputError(f'{where}: {shown(value)} is not a finite number')
    return number


def _described(document, top=True):
    """Say what a parsed YAML or JSON document (or, not `top`, a value in one) is."""
    if document is None and top:
        return 'nothing (an empty document)'
    if isinstance(document, str) and top:   # (a CSV, or any text, reads as one YAML string)
        return 'plain text, not YAML or JSON structure (a samples CSV? --format csv reads one)'
    if isinstance(document, dict):
        keys = list(document)
        more = ', ...' if len(keys) > 5 else ''
        return (f'a mapping with {", ".join(map(str, keys[:5]))}{more}' if keys
                else 'an empty mapping')
    if isinstance(document, list):
        return f'a list of {len(document)} entries'
    return f'{type(document).__name__} {shown(repr(document))}'


def _mapping(value, where, keys, top=False):
    if not isinstance(value, dict):
        raise BadInputError(f'{where}: expected a mapping with {", ".join(keys)}, got '
                            f'{_described(value, top)}')
    missing = [key for key in keys if key not in value]
    if missing:
        raise BadInputError(f'{where}: missing {", ".join(missing)}')
    return value


def _position(values, where):
    """Return the position, or raise BadInputError naming `where` (units.position_problem)."""
    problem = position_problem(values)
    if problem:
        raise BadInputError(f'{where}: {problem}')
    return values


def _transform(value, where, field_name):
    """Pose of a geometry_msgs/Transform-shaped mapping (translation, rotation x, y, z, w)."""
    prefix = f'{where}, field {field_name}'
    value = _mapping(value, prefix, ('translation', 'rotation'))
    translation = _mapping(value['translation'], f'{prefix}.translation', 'xyz')
    rotation = _mapping(value['rotation'], f'{prefix}.rotation', 'xyzw')
    position = _position([_number(translation[axis], f'{prefix}.translation.{axis}')
                          for axis in 'xyz'], f'{prefix}.translation')
    xyzw = [_number(rotation[axis], f'{prefix}.rotation.{axis}') for axis in 'xyzw']
    problem = quaternion_norm_problem(xyzw, FILE_NORM_TOLERANCE)
    if problem:
        raise BadInputError(f'{prefix}.rotation: {problem}; quaternions are x, y, z, w')
    return Pose.create(position, wxyz_from_xyzw(xyzw))


def _matrix_pose(value, where, field_name):
    """Pose of a 4x4 homogeneous matrix: 16 numbers row-major, or 4 rows of 4."""
    prefix = f'{where}, field {field_name}'
    if not isinstance(value, (list, tuple)):
        raise BadInputError(f'{prefix}: expected a 4x4 matrix (16 numbers, row-major), got '
                            f'{type(value).__name__} {shown(repr(value))}')
    if len(value) == 4 and all(isinstance(row, (list, tuple)) for row in value):
        if any(len(row) != 4 for row in value):
            raise BadInputError(f'{prefix}: expected 4 rows of 4 numbers, got rows of '
                                f'{", ".join(str(len(row)) for row in value)}')
        flat = [v for row in value for v in row]
    else:
        flat = list(value)
        if len(flat) != 16:
            raise BadInputError(f'{prefix}: expected 16 numbers (a 4x4 matrix, row-major), '
                                f'got {len(flat)}')
    numbers = [_number(v, f'{prefix}[{k // 4}][{k % 4}]') for k, v in enumerate(flat)]
    H = np.array(numbers).reshape(4, 4)
    if not np.allclose(H[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise BadInputError(f'{prefix}: the last row is {H[3].tolist()}, not [0, 0, 0, 1]: '
                            'not a homogeneous transform')
    R = H[:3, :3]
    with np.errstate(over='ignore', invalid='ignore'):   # (1e200: inf, refused below)
        error = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if error <= ROTATION_TOLERANCE and np.linalg.det(R) < 0.0:
        raise BadInputError(f'{prefix}: the upper-left 3x3 block is a reflection (determinant '
                            f'{np.linalg.det(R):.3g}), not a rotation: one axis of a frame is '
                            'flipped (a left-handed frame, or a sign lost in a conversion)')
    if not error <= ROTATION_TOLERANCE:
        raise BadInputError(f'{prefix}: the upper-left 3x3 block is not a rotation matrix '
                            f'(|R^T R - I| = {error:.3g}, det {np.linalg.det(R):.3g}); is the '
                            'matrix transposed or scaled?')
    # Project onto the nearest rotation (rounding in the file), as a unit quaternion.
    return Pose.create(_position(H[:3, 3].tolist(), f'{prefix}, last column'),
                       quaternion_from_matrix(R))


def _stamp(index):
    return index * NS_PER_S


def _check_setup(setup):
    if setup not in (None, 'eye_in_hand', 'eye_to_hand'):
        raise ValueError(f'setup must be eye_in_hand or eye_to_hand, not {setup!r}')


# --- easy_handeye2 ---------------------------------------------------------------------------

def parse_easy_handeye2_samples(document, name='<easy_handeye2 samples>', setup=None):
    """
    Read the samples of a parsed easy_handeye2 SampleList document (see module docstring).

    :param setup: 'eye_in_hand' or 'eye_to_hand' when the caller knows it; None: from the
        file's calibration_type, else eye_in_hand.  A file that names the other setup is bad
        input (its robot transforms point the other way).
    :return: ImportedSamples (format 'easy_handeye2').
    """
    _check_setup(setup)
    document = _mapping(document, f'{name}: the top level', ('samples',), top=True)
    parameters = document.get('parameters') or {}
    if not isinstance(parameters, dict):
        raise BadInputError(f'{name}, field parameters: expected a mapping, got '
                            f'{type(parameters).__name__}')
    calibration_type = str(parameters.get('calibration_type') or '').strip()
    file_setup = None
    if calibration_type:
        file_setup = exports.SETUPS_BY_EASY_HANDEYE2_TYPE.get(calibration_type)
        if file_setup is None:
            raise BadInputError(f'{name}, field parameters.calibration_type: '
                                f'{calibration_type!r} is not eye_in_hand or eye_on_base')
        if setup is not None and setup != file_setup:
            raise BadInputError(
                f'{name}, field parameters.calibration_type: the file was recorded as '
                f'{calibration_type} ({file_setup}) but --setup {setup} was given; '
                'easy_handeye2 stores the robot transform the other way round for '
                'eye_on_base, so the setup must match the recording')
    use_setup = setup or file_setup or 'eye_in_hand'
    warnings = []
    if not calibration_type and setup is None:
        # robot = T_effector_base (eye_on_base) turns eye_in_hand's motions inv(L_i) L_j into
        # eye_to_hand's L_i inv(L_j): both setups fit equally well, the data cannot tell.
        warnings.append(
            f'{name} does not name its calibration_type (easy_handeye2 leaves it empty): '
            'solved as eye_in_hand; if it was recorded as eye_on_base, pass --setup '
            'eye_to_hand (the numbers are the same, the frames are the base and the camera)')
    entries = document['samples']
    if entries is None:
        entries = []
    if not isinstance(entries, list):
        raise BadInputError(f'{name}, field samples: expected a list of samples, got '
                            f'{type(entries).__name__}')
    samples = []
    for i, entry in enumerate(entries):
        where = f'{name}, entry samples[{i}]'
        entry = _mapping(entry, where, ('robot', 'tracking'))
        robot = _transform(entry['robot'], where, 'robot')
        tracking = _transform(entry['tracking'], where, 'tracking')
        link = robot if use_setup == 'eye_in_hand' else robot.inverse()
        samples.append(Sample(_stamp(i), link, tracking))
    frames = {key: _frame_name(parameters[key], f'{name}, field parameters.{key}') for key in (
        'robot_base_frame', 'robot_effector_frame', 'tracking_base_frame',
        'tracking_marker_frame') if parameters.get(key)}
    return ImportedSamples(samples, 'easy_handeye2', file_setup, frames, warnings)


def _frame_name(value, where):
    """Return a frame name of the file: text, or a whole number (YAML reads a bare 1 so)."""
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise BadInputError(f'{where}: expected a frame name, got {type(value).__name__} '
                            f'{shown(repr(value))}')
    return str(value)


def read_easy_handeye2_samples(path, setup=None):
    """
    Read an easy_handeye2 `.samples` file as a list of pose.Sample.

    Link poses are T_base_effector (turned back from easy_handeye2's T_effector_base for
    eye_on_base), sensor poses T_tracking_marker.  See parse_easy_handeye2_samples for
    `setup`; raises BadInputError naming the file, entry and field.
    """
    return load_samples(path, 'easy_handeye2', setup).samples


# --- moveit_calibration ----------------------------------------------------------------------

def parse_moveit_samples(document, name='<moveit samples>'):
    """Read a parsed moveit_calibration samples YAML (list of 16-number matrices)."""
    if not isinstance(document, list):
        raise BadInputError(f'{name}: expected a list of samples with effector_wrt_world and '
                            f'object_wrt_sensor, got {_described(document)}')
    samples = []
    for i, entry in enumerate(document):
        where = f'{name}, entry [{i}]'
        entry = _mapping(entry, where, ('effector_wrt_world', 'object_wrt_sensor'))
        samples.append(Sample(_stamp(i),
                              _matrix_pose(entry['effector_wrt_world'], where,
                                           'effector_wrt_world'),
                              _matrix_pose(entry['object_wrt_sensor'], where,
                                           'object_wrt_sensor')))
    return ImportedSamples(samples, 'moveit')


def parse_moveit_json_samples(document, name='<moveit json samples>'):
    """Read a parsed moveit_calibration pose_samples.json: [[eef_wrt_world, obj_wrt_sensor]]."""
    if not isinstance(document, list):
        raise BadInputError(f'{name}: expected a list of [eef_wrt_world, obj_wrt_sensor] '
                            f'pairs, got {_described(document)}')
    samples = []
    for i, entry in enumerate(document):
        where = f'{name}, entry [{i}]'
        if not isinstance(entry, list) or len(entry) != 2:
            raise BadInputError(f'{where}: expected a pair [eef_wrt_world, obj_wrt_sensor] '
                                f'of 4x4 matrices, got {shown(repr(entry))}')
        samples.append(Sample(_stamp(i), _matrix_pose(entry[0], where, 'eef_wrt_world'),
                              _matrix_pose(entry[1], where, 'obj_wrt_sensor')))
    return ImportedSamples(samples, 'moveit-json')


def read_moveit_json_samples(path):
    """Read moveit_calibration's pose_samples.json layout as a list of pose.Sample."""
    return load_samples(path, 'moveit-json').samples


# --- any samples file ------------------------------------------------------------------------

def _is_csv(text):
    for line in text.splitlines():
        stripped = line.strip()
        if stripped and not stripped.startswith('#'):
            return stripped.startswith('stamp') and ',' in stripped
    return False


def detect_format(document):
    """Return the format of parsed YAML/JSON content, or None when it is none of ours."""
    if isinstance(document, dict) and 'samples' in document:
        return 'easy_handeye2'
    if isinstance(document, list) and document:
        first = document[0]
        if isinstance(first, dict) and ('effector_wrt_world' in first
                                        or 'object_wrt_sensor' in first):
            return 'moveit'
        if isinstance(first, list) and len(first) == 2:
            return 'moveit-json'
    return None


def _csv_samples(text, name, setup=None, invert_sensor=None):
    """
    Return the ImportedSamples of a samples CSV's text, read from `name`.

    A samples journal's header names its setup, frames (the link frame is the parent: the
    effector eye-in-hand, the base eye-to-hand) and invert_sensor. A journal holds the poses
    as received, so another `setup` or `invert_sensor` may solve it (what a convention warning
    asks for); then a warning says so, and with another setup the header's frames, named for
    its own, are not used.
    """
    first = text.split('\n', 1)[0].rstrip('\r')
    if not first.startswith(journal.MAGIC):
        samples, rows = parse_samples_and_rows(text, name)
        return ImportedSamples(samples, 'csv', invert_sensor=invert_sensor, rows=rows)
    try:
        header = journal.JournalHeader.parse(first, name)
    except journal.JournalError as error:
        raise BadInputError(str(error)) from None
    # A journal's last line may be one a crash interrupted: dropped, as the node's resume does.
    end = text.rfind('\n') + 1
    text, warnings = journal.complete_lines(text[:end], name, len(text[end:].encode('utf-8')))
    samples, rows = parse_samples_and_rows(text, name)
    recorded = header.invert_sensor
    if invert_sensor is not None and recorded is not None and invert_sensor != recorded:
        warnings.append(f'{name}: the journal was recorded with invert_sensor '
                        f'{journal.boolean_text(recorded)}; it is solved with '
                        f'{journal.boolean_text(invert_sensor)}, as the options say')
    invert = recorded if invert_sensor is None else invert_sensor
    if setup is not None and setup != header.setup:
        said = (f'{name}: the journal was recorded with setup {header.setup}; it is solved as '
                f'{setup}, as --setup says (its frame names, {header.link_frame} -> '
                f'{header.sensor_frame}, belong to {header.setup} and are not used)')
        return ImportedSamples(samples, 'csv', setup, invert_sensor=invert, rows=rows,
                               warnings=[*warnings, said])
    parent = 'robot_effector_frame' if header.setup == 'eye_in_hand' else 'robot_base_frame'
    frames = {parent: header.link_frame, 'tracking_base_frame': header.sensor_frame}
    if journal.unnamed_base(header):   # the default base names it, as a resumed node does
        del frames[parent]
        warnings.append(f'{name}: an eye_to_hand journal of an earlier version, whose '
                        f'link_frame {header.link_frame} is the default flange name, not the '
                        'robot base: the result is named from the default base frame (give '
                        '--parent-frame to name it)')
    return ImportedSamples(samples, 'csv', header.setup, frames, warnings, invert,
                           header.static_chain, rows)


def _not_ours(name):
    """Say that file `name` is in none of the formats (content guessed)."""
    return (f'{name}: not a samples file this tool knows: expected a samples CSV, an '
            'easy_handeye2 .samples YAML (parameters, samples: [{robot, tracking}]), a '
            'moveit_calibration samples YAML ([{effector_wrt_world, object_wrt_sensor}]) or a '
            'moveit pose_samples.json ([[eef_wrt_world, obj_wrt_sensor]]); pass --format to '
            'say which')


def load_samples(path, file_format='auto', setup=None, invert_sensor=None):
    """
    Read still samples from a samples CSV or another tool's samples file.

    :param path: the file.
    :param file_format: 'auto' (by the extension, then by the content) or one of FORMATS.
    :param setup: the setup, when known (easy_handeye2 files depend on it; see
        parse_easy_handeye2_samples; a journal recorded with another says so, _csv_samples);
        other formats ignore it.
    :param invert_sensor: whether to invert the sensor poses, when the caller was told; else
        a journal's header says (_csv_samples), or None.
    :return: ImportedSamples.
    :raises BadInputError: naming the file, entry and field.
    """
    if file_format != 'auto' and file_format not in FORMATS:
        raise ValueError(f'format must be auto or one of {", ".join(FORMATS)}, not '
                         f'{file_format!r}')
    _check_setup(setup)
    name = str(path)
    suffix = Path(name).suffix.lower()
    if file_format == 'auto':
        file_format = SUFFIX_FORMATS.get(suffix, 'auto')
    text = read_text(path)   # once: a pipe cannot be read twice
    if file_format == 'csv' or file_format == 'auto' and _is_csv(text):
        return _csv_samples(text, name, setup, invert_sensor)
    if not text.strip():
        raise BadInputError(f'{name}: empty file')
    as_json = file_format == 'moveit-json' or suffix == '.json'
    try:
        document = _load_json(text, name) if as_json else _load_yaml(text, name)
    except BadInputError as error:
        if file_format != 'auto':
            raise
        said = str(error).removeprefix(f'{name}, ')
        raise BadInputError(f'{_not_ours(name)} (read as {"JSON" if as_json else "YAML"}: '
                            f'{said})') from None
    if file_format == 'auto':
        file_format = detect_format(document)
        if file_format is None:
            raise BadInputError(_not_ours(name))
    if file_format == 'easy_handeye2':
        imported = parse_easy_handeye2_samples(document, name, setup)
    elif file_format == 'moveit':
        imported = parse_moveit_samples(document, name)
    else:
        imported = parse_moveit_json_samples(document, name)
    return replace(imported, invert_sensor=invert_sensor)   # (it was lost for these formats)


# --- writers (tests, and moving samples to those tools) -------------------------------------

def _transform_dict(pose):
    return {'translation': xyz_json(pose.position), 'rotation': xyzw_json(pose.quaternion)}


def format_easy_handeye2_samples(samples, setup='eye_in_hand', parameters=None):
    """
    Return easy_handeye2 `.samples` YAML of `samples` (list of pose.Sample), as it saves them.

    For eye_to_hand the robot transform is written as T_effector_base, as easy_handeye2 does.
    parameters: values for the `parameters` mapping (all left empty unless given, as
    easy_handeye2 itself leaves them; a file written for eye_to_hand therefore re-imports as
    eye_in_hand unless --setup or a calibration_type in `parameters` says otherwise).
    """
    _check_setup(setup)
    params = {'name': '', 'calibration_type': '', 'robot_base_frame': '',
              'robot_effector_frame': '', 'tracking_base_frame': '',
              'tracking_marker_frame': '', 'freehand_robot_movement': False,
              'move_group_namespace': '/', 'move_group': 'manipulator'}
    params.update(parameters or {})
    entries = []
    for sample in samples:
        robot = sample.link if setup == 'eye_in_hand' else sample.link.inverse()
        entries.append({'robot': _transform_dict(robot),
                        'tracking': _transform_dict(sample.sensor)})
    return plain_yaml.dump({'parameters': params, 'samples': entries}, sort_keys=False,
                           default_flow_style=False)


def format_moveit_samples(samples):
    """Return moveit_calibration samples YAML of `samples`: 16 numbers row-major each."""
    entries = [{'effector_wrt_world': [float(v) for v in s.link.as_matrix().ravel()],
                'object_wrt_sensor': [float(v) for v in s.sensor.as_matrix().ravel()]}
               for s in samples]
    return plain_yaml.dump(entries, sort_keys=False, default_flow_style=None)
