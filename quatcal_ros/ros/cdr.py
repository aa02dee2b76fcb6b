"""
Stamps and poses straight from the raw CDR bytes of PoseStamped and TransformStamped messages.

The bag replay's fast path: many messages at once, with numpy, instead of deserialising each
into message objects first.  A message (little-endian CDR, as ROS 2 records it) is a 4-byte
encapsulation header, then header.stamp (int32 sec, uint32 nanosec), header.frame_id (uint32
length counting the NUL, the text, the NUL), for TransformStamped child_frame_id (aligned to
4), then the seven float64 (aligned to 8 from the end of the encapsulation header) of
position x, y, z and orientation x, y, z, w (TransformStamped: translation, rotation).

`decode_pose` does the same for one message (the live node's raw subscriptions): struct, no
numpy, no message objects.

A message is decoded only when rosbags would read it and conversions would accept it at once:
the layout checks out, the frame ids are ASCII, the nanosec is in range, the position finite
and the quaternion norm within the tolerance (renormalised as conversions.pose_from_msg does,
with the same arithmetic, so the numbers are bit for bit the same).  Anything else is left to
rosbags and conversions, which decode it or say why not.
"""

from functools import lru_cache
import struct
from typing import NamedTuple

import numpy as np

from quatcal_ros.core.units import MAX_POSITION_M, MESSAGE_NORM_TOLERANCE, NS_PER_S
from quatcal_ros.stream.tf_tree import normalize_frame

# Strings before the pose: header.frame_id (and child_frame_id), by message type.
STRINGS_BEFORE_POSE = {'geometry_msgs/msg/PoseStamped': 1,
                       'geometry_msgs/msg/TransformStamped': 2}
CDR_LE = (0, 1)             # the encapsulation header's first two bytes
HEADER = 4                  # bytes before the CDR body, where alignment starts
POSE_VALUES = 7
WXYZ = [6, 3, 4, 5]         # the quaternion's columns among the pose values, scalar first
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')
_POSE = struct.Struct('<7d')


class DecodedPoses(NamedTuple):
    """
    Poses of n raw messages; only the rows where `ok` is set hold numbers.

    stamps_ns (n,) int64 header stamps; positions (n, 3); quaternions (n, 4) unit, (w, x, y, z).
    """

    stamps_ns: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    ok: np.ndarray


def decode_poses(raws, msgtype, norm_tolerance=MESSAGE_NORM_TOLERANCE, frame_id='',
                 max_position_m=MAX_POSITION_M):
    """
    Decode raw CDR messages of type `msgtype` (a key of STRINGS_BEFORE_POSE); a DecodedPoses.

    Rows not `ok` are left to rosbags' deserialisation, conversions and the message checks
    (module docstring); so are zero stamps and, when `frame_id` is given, every header frame
    other than exactly that one, and positions beyond max_position_m (the message checks
    decide what they are).
    """
    strings = STRINGS_BEFORE_POSE[msgtype]
    count = len(raws)
    stamps = np.zeros(count, dtype=np.int64)
    values = np.zeros((count, POSE_VALUES))
    ok = np.zeros(count, dtype=bool)
    left = list(range(count))   # rows not looked at yet
    while left:
        rows, records = _records(raws, left, strings)
        if records is not None:
            ok[rows] = _well_formed(records, strings) & _frame_is(records, frame_id)
            stamps[rows] = records['sec'] * np.int64(NS_PER_S) + records['nanosec']
            values[rows] = records['pose']
        taken = set(rows)
        left = [row for row in left if row not in taken]
    positions, quaternions, usable = _pose_values(values, norm_tolerance)
    with np.errstate(invalid='ignore'):
        near = (np.abs(positions) <= max_position_m).all(axis=1)
    return DecodedPoses(stamps, positions, quaternions, ok & usable & near & (stamps != 0))


def decode_pose(raw, msgtype):
    """
    Return (stamp_ns, frame_id, seven pose floats) of one raw message of `msgtype`, or None.

    The floats: position x, y, z, then the quaternion x, y, z, w, as the message holds them
    (conversions.pose_from_values checks and normalises them). None when the bytes are not
    laid out as decode_poses vouches for (the caller deserialises the message instead, which
    decodes it or says why not). The stamp and frame id are not judged here: the message
    checks do that, as for every message.
    """
    strings = _strings(raw, msgtype)
    if strings is None:
        return None
    texts, pose_at = strings
    sec, nanosec = _STAMP.unpack_from(raw, HEADER)
    if nanosec >= NS_PER_S:
        return None
    return sec * NS_PER_S + nanosec, texts[0], _POSE.unpack_from(raw, pose_at)


def frame_ids(raw, msgtype):
    """
    Return (header.frame_id, child_frame_id or None) of one raw message, without '/'.

    As conversions.frame_ids of the message; None when decode_pose would not vouch for it.
    """
    strings = _strings(raw, msgtype)
    if strings is None:
        return None
    texts = [normalize_frame(text) for text in strings[0]]
    return texts[0], texts[1] if len(texts) > 1 else None


def _strings(raw, msgtype):
    """Return the strings before the pose of a raw message and where its pose starts, or None."""
    strings = STRINGS_BEFORE_POSE[msgtype]
    if raw[:2] != _CDR_LE_BYTES:
        return None
    lengths = _string_lengths(raw, strings)
    offsets = _offsets(strings, len(raw), lengths)
    if offsets is None:
        return None
    at_texts, pose_at = offsets
    texts = []
    for at, size in zip(at_texts, lengths):
        text = raw[at:at + size]
        if text[-1] != 0 or not text.isascii():
            return None
        texts.append(text[:-1].decode('ascii'))
    return texts, pose_at


_CDR_LE_BYTES = bytes(CDR_LE)


@lru_cache(maxsize=64)
def _offsets(strings, length, string_lengths):
    """Return (the strings' text offsets, the pose's offset) of _layout's record, or None."""
    layout = _layout(strings, length, string_lengths)
    if layout is None:
        return None
    return (tuple(layout.fields[f'text{index}'][1] for index in range(strings)),
            layout.fields['pose'][1])


def _records(raws, rows, strings):
    """
    Return (rows, their numpy records) of the messages of `rows` laid out as the first one.

    In practice one layout serves a whole run.  ([first row], None) when rosbags would not
    read the first one (its layout does not check out).
    """
    first = raws[rows[0]]
    layout = _layout(strings, len(first), _string_lengths(first, strings))
    if layout is None:
        return rows[:1], None
    rows = [row for row in rows if len(raws[row]) == len(first)]
    records = np.frombuffer(b''.join([raws[row] for row in rows]), dtype=layout)
    fits = np.ones(len(records), dtype=bool)
    for index in range(strings):
        fits &= records[f'length{index}'] == records.dtype[f'text{index}'].shape[0]
    if fits.all():
        return rows, records
    return [row for row, fit in zip(rows, fits) if fit], records[fits]


def _string_lengths(raw, strings):
    """Return the length fields of the first `strings` strings of `raw`, or None if cut short."""
    lengths, at = [], HEADER + 8
    for _ in range(strings):
        at = HEADER + _align(at - HEADER, 4)
        if at + 4 > len(raw):
            return None
        length = _U32.unpack_from(raw, at)[0]
        lengths.append(length)
        at += 4 + length
    return tuple(lengths)


def _align(offset, size):
    return (offset + size - 1) & -size


@lru_cache(maxsize=64)
def _layout(strings, length, string_lengths):
    """
    Return the numpy record of messages of `length` bytes with these string lengths, or None.

    None when rosbags would not read such a message: a string without room for its NUL, or
    a body that does not end with the pose (up to 3 bytes of padding may follow).
    """
    if string_lengths is None or len(string_lengths) != strings:
        return None
    fields = {'cdr': (0, ('u1', 2)), 'sec': (HEADER, '<i4'), 'nanosec': (HEADER + 4, '<u4')}
    at = 8   # in the body
    for index, size in enumerate(string_lengths):
        at = _align(at, 4)
        if size < 1 or HEADER + at + 4 + size > length:
            return None
        fields[f'length{index}'] = (HEADER + at, '<u4')
        fields[f'text{index}'] = (HEADER + at + 4, ('u1', size))
        at += 4 + size
    at = _align(at, 8)
    end = HEADER + at + 8 * POSE_VALUES
    if not 0 <= length - end <= 3:
        return None
    fields['pose'] = (HEADER + at, ('<f8', POSE_VALUES))
    names = list(fields)
    return np.dtype({'names': names, 'offsets': [fields[n][0] for n in names],
                     'formats': [fields[n][1] for n in names], 'itemsize': length})


def _well_formed(records, strings):
    """Return which records rosbags reads as they are: CDR LE, NUL-terminated ASCII strings."""
    ok = (records['cdr'] == CDR_LE).all(axis=1) & (records['nanosec'] < NS_PER_S)
    for index in range(strings):
        text = records[f'text{index}']
        ok &= (text[:, -1] == 0) & (text < 0x80).all(axis=1)
    return ok


def _frame_is(records, frame_id):
    """Return which records have header.frame_id `frame_id` exactly (all when it is '')."""
    if not frame_id:
        return np.ones(len(records), dtype=bool)
    expected = np.frombuffer(frame_id.encode('utf-8') + b'\0', dtype=np.uint8)
    text = records['text0']
    if text.shape[1] != len(expected):
        return np.zeros(len(records), dtype=bool)
    return (text == expected).all(axis=1)


def _pose_values(values, norm_tolerance):
    """
    Return (positions, quaternions (w, x, y, z), usable) of (n, 7) pose values.

    The arithmetic of conversions.pose_from_msg, term for term: a finite sum of the position
    and a quaternion norm within the tolerance; the quaternion divided by its norm.
    """
    x, y, z, qx, qy, qz, qw = values.T
    with np.errstate(invalid='ignore', over='ignore', divide='ignore'):
        norm = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        usable = np.isfinite(x + y + z) & (np.abs(norm - 1.0) <= norm_tolerance)
        quaternions = values[:, WXYZ] / norm[:, None]
    return values[:, :3].copy(), quaternions, usable


def stretches(flags):
    """Return [(start, stop, flag)] of the stretches of equal flags of a non-empty bool array."""
    if flags.all():
        return [(0, len(flags), True)]
    bounds = [0, *(np.flatnonzero(flags[1:] != flags[:-1]) + 1).tolist(), len(flags)]
    return [(start, stop, bool(flags[start])) for start, stop in zip(bounds, bounds[1:])]
