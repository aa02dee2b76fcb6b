"""
Files that must survive a crash: atomic writes and the calibration result YAML.

`atomic_write_text` / `atomic_write_bytes` write a temporary file in the target's directory,
fsync it, rename it over the target with os.replace and fsync the directory, so a reader sees
either the old file or the new one, never a torn one.

The result YAML (written by the live node's ~/save and by the bag replay) is the whole
mounting, format quatcal_ros/mounting version 2:

    parent_frame: tool0          # link frame (eye_in_hand) or base frame (eye_to_hand)
    child_frame: camera          # sensor frame
    setup: eye_in_hand
    method: refined              # which estimate rotation/translation hold
    rotation: {x: .., y: .., z: .., w: ..}   # quaternion x, y, z, w (ROS order), parent -> child
    translation: {x: .., y: .., z: ..}       # metres, the child's origin in the parent frame
    matrix: [[..], [..], [..]]               # rotation matrix, child coordinates -> parent
    quality: {samples, motions, inliers, residual_rms_deg, uncertainty_deg,
              translation_uncertainty_mm}
    estimates:                               # both, each with its own uncertainty
      closed_form: {rotation, translation, uncertainty_deg, translation_uncertainty_mm}
      refined: {..}                          # null when the refinement did not run
    hint: ..
    warnings: [..]
    urdf: ..                                 # the fixed joint parent_frame -> child_frame
    xacro: ..                                # the same as a xacro macro
    validation: {verdict, reason, rms_rotation_deg, rms_translation_mm, thresholds, worst}
                                             # the leave-one-out check (added in version 2;
                                             # per-sample errors are in the JSON only)

Version 1 files (format quatcal_ros/rotation: the rotation alone) still read.

The core's quaternions are (w, x, y, z); this file is the boundary where they become x, y, z, w.
No rclpy here: the module is plain Python for every tool.
"""

import errno
import os
from pathlib import Path
import tempfile

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.numerics import finite_or_none
from quatcal_ros.files import exports
from quatcal_ros.files import plain_yaml

RESULT_FORMAT = 'quatcal_ros/mounting'
RESULT_FORMAT_VERSION = 2
# Formats read back: this one, and version 1 (the rotation alone).
READABLE_FORMATS = {('quatcal_ros/rotation', 1), (RESULT_FORMAT, RESULT_FORMAT_VERSION)}
QUALITY_FIELDS = ('samples', 'motions', 'inliers', 'residual_rms_deg', 'uncertainty_deg',
                  'translation_uncertainty_mm')


def atomic_write_bytes(path, data, mode=0o644):
    """
    Replace the file `path` by `data` atomically; create missing parent directories.

    A symbolic link is followed: the file it points to is replaced, the link stays. An
    existing file keeps its permission bits; a new one gets `mode` less the umask, as open()
    gives; created directories are made durable too.

    :param path: target file (str or path-like); `~` is expanded.
    :param data: bytes to write.
    :param mode: permission bits of a new file, before the umask.
    :return: the target as an absolute pathlib.Path.
    :raises OSError: when the directory cannot be created or written (a symbolic link loop
        too); the target is unchanged.
    """
    target = Path(path).expanduser().absolute()
    if target.is_symlink():
        target = Path(os.path.realpath(target, strict=False))
        if target.is_symlink():   # realpath stops at a loop
            raise OSError(errno.ELOOP, 'a loop of symbolic links; nothing was written',
                          str(path))
    if target.exists() and not target.is_file():
        # A device (/dev/null), a pipe or a directory is never renamed over.
        raise OSError(errno.EEXIST, 'exists and is not a regular file; nothing was written',
                      str(target))
    if target.exists():
        mode = target.stat().st_mode & 0o7777
    else:
        mode &= ~_umask()
    created = [d for d in target.parents if not d.exists()]
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:   # an ancestor of the target is a file
        blocking = next((p for p in target.parents if p.exists() and not p.is_dir()),
                        target.parent)
        raise OSError(errno.ENOTDIR, 'a parent is a file, not a directory',
                      str(blocking)) from None
    fd, tmp_name = tempfile.mkstemp(prefix='.' + target.name + '.', suffix='.tmp',
                                    dir=target.parent)
    try:
        with os.fdopen(fd, 'wb') as tmp:
            tmp.write(data)
            tmp.flush()
            os.fsync(tmp.fileno())
        os.chmod(tmp_name, mode)
        os.replace(tmp_name, target)
    except BaseException:
        _remove_quietly(tmp_name)
        raise
    _fsync_directory(target.parent)
    for folder in created:   # their entries in their parents, innermost first
        _fsync_directory(folder.parent)
    return target


def _umask():
    """
    Return the process's umask.

    From /proc (Linux): setting it to read it, as os.umask must, would change it for a
    moment for the node's other threads too.
    """
    try:
        with open('/proc/self/status', encoding='ascii') as status:
            for line in status:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)   # pragma: no cover - no /proc
    os.umask(mask)
    return mask


def atomic_write_text(path, text, mode=0o644, encoding='utf-8'):
    """Replace the file `path` by `text` atomically (see atomic_write_bytes)."""
    return atomic_write_bytes(path, text.encode(encoding), mode=mode)


def _remove_quietly(name):
    try:
        os.unlink(name)
    except OSError:
        pass


def _fsync_directory(directory):
    """Make the rename durable; some file systems cannot open a directory, which is fine."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _plain_number(value):
    """Python int or float for YAML; NaN and inf become None (null), which all readers accept."""
    if value is None:
        return None
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return int(value)
    return finite_or_none(value)


def _plain_numbers(value):
    """Return `value` (JSON-like: dicts, lists, numbers, text) with _plain_number's floats."""
    if isinstance(value, dict):
        return {key: _plain_numbers(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_plain_numbers(item) for item in value]
    return _plain_number(value) if isinstance(value, float) else value


def result_document(result, parent_frame, child_frame, setup='eye_in_hand', extra=None,
                    joint=None):
    """
    Build the result YAML's content as plain Python types.

    :param result: a calibration.CalibrationResult (quaternion (w, x, y, z), matrix, samples,
        motions, inliers, residual_rms_deg, uncertainty_deg, hint, warnings).
    :param parent_frame: link frame (eye_in_hand) or robot base frame (eye_to_hand).
    :param child_frame: sensor frame.
    :param setup: 'eye_in_hand' or 'eye_to_hand'.
    :param extra: optional dict of further top-level keys (for example the source bag).
    :param joint: the stream.tf_joint.Joint of the "urdf" and "xacro" keys (with TF input:
        the joint the transform tree can take), or None: parent_frame -> child_frame.
    :return: a dict that yaml.safe_dump accepts.
    """
    w, x, y, z = (float(c) for c in np.asarray(result.quaternion, dtype=float).reshape(4))
    matrix = np.asarray(result.matrix, dtype=float).reshape(3, 3)
    quality = {name: _plain_number(getattr(result, name, None)) for name in QUALITY_FIELDS}
    translation = getattr(result, 'translation', None)
    document = {
        'format': RESULT_FORMAT,
        'format_version': RESULT_FORMAT_VERSION,
        'parent_frame': str(parent_frame),
        'child_frame': str(child_frame),
        'setup': str(setup),
        'invert_sensor': bool(getattr(result, 'invert_sensor', False)),
        'method': str(getattr(result, 'method', '') or ''),
        'rotation': {'x': x, 'y': y, 'z': z, 'w': w},
        'translation': None if translation is None else quat.xyz_json(
            np.asarray(translation, dtype=float).reshape(3)),
        'matrix': [[float(v) for v in row] for row in matrix],
        'quality': quality,
        'estimates': {name: _estimate(getattr(result, name, None))
                      for name in ('closed_form', 'refined')},
        'hint': str(getattr(result, 'hint', '') or ''),
        'warnings': [str(text) for text in (getattr(result, 'warnings', None) or [])],
        # false when a warning says not to use the estimate (CalibrationResult.usable)
        'usable': bool(getattr(result, 'usable', True)),
    }
    try:   # the fixed joint of the mounting, to commit into the robot description
        document.update(exports.description_joints(result, parent_frame, child_frame)
                        if joint is None else exports.description_joints(
                            joint.result, joint.parent, joint.child, joint.note))
    except (AttributeError, ValueError):   # no (finite) translation
        pass
    reprojection = getattr(result, 'reprojection', None)
    if reprojection:   # the fit on the pixels: its pixel noise and views' errors
        document['reprojection'] = _plain_numbers(reprojection)
    validation = getattr(result, 'validation', None)
    if validation:
        document['validation'] = {key: value for key, value in validation.items()
                                  if key != 'samples'}
    if extra:
        document.update(extra)
    return document


def _estimate(estimate):
    """Return one calibration.Estimate as plain data (its JSON form), or None."""
    if estimate is None:
        return None
    document = estimate.to_json_dict()
    return {key: (_plain_number(value) if key.endswith(('_deg', '_mm')) else value)
            for key, value in document.items()}


def format_result_yaml(result, parent_frame, child_frame, setup='eye_in_hand', extra=None,
                       joint=None):
    """Return the result YAML text (see result_document for the arguments)."""
    document = result_document(result, parent_frame, child_frame, setup, extra, joint)
    header = ('# Hand-eye calibration by quatcal_ros (Chou and Kamel 1988): the mounting.\n'
              '# rotation (quaternion x, y, z, w) and translation (m) of the transform\n'
              '# parent_frame -> child_frame; matrix maps child_frame coordinates to\n'
              '# parent_frame coordinates.\n')
    return header + plain_yaml.dump(document, sort_keys=False, default_flow_style=None)


def write_result_yaml(path, result, parent_frame, child_frame, setup='eye_in_hand',
                      extra=None, joint=None):
    """
    Write the result YAML to `path` atomically; return the absolute path written.

    :raises OSError: when the file cannot be written (the previous file, if any, is kept).
    """
    text = format_result_yaml(result, parent_frame, child_frame, setup, extra, joint)
    return atomic_write_text(path, text)


def read_result_yaml(path):
    """
    Read a result YAML back.

    :return: the document (dict) with 'quaternion_xyzw' added as a numpy array (x, y, z, w).
    :raises ValueError: when the file cannot be read (text_input.BadInputError) or is not a
        result YAML (the message names the file), including YAML that asks for objects
        (python/... tags): the file is data, read with the safe loader, which builds only
        mappings, lists, strings and numbers.
    """
    path = Path(path).expanduser()
    document = plain_yaml.load_file(path, holds='a result file')
    if not isinstance(document, dict):
        raise ValueError(f'{path}: not a quatcal_ros result file (no mapping at the top)')
    kind = (document.get('format'), document.get('format_version', 1))
    if 'format' in document and kind not in READABLE_FORMATS:
        raise ValueError(f'{path}: format {kind[0]} version {kind[1]} is not one this version '
                         'reads (' + ', '.join(f'{f} {v}' for f, v in sorted(READABLE_FORMATS))
                         + ')')
    try:
        rotation = document['rotation']
        q = np.array([rotation[k] for k in ('x', 'y', 'z', 'w')], dtype=float)
    except (KeyError, TypeError) as error:
        raise ValueError(f'{path}: not a quatcal_ros result file (no rotation x, y, z, w: '
                         f'{error})') from None
    document['quaternion_xyzw'] = q
    translation = document.get('translation')   # version 1: none
    document['translation_xyz'] = None if translation is None else np.array(
        [translation[k] for k in 'xyz'], dtype=float)
    return document
