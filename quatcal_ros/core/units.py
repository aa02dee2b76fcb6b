"""
The project's vocabulary: units, the two setups, and what every reader shares.

Times are header stamps in integer nanoseconds in the core (DESIGN.md, conventions); users
speak seconds, degrees and metres.  A quaternion read from a file or a command line is
checked by `quaternion_norm_problem` (FILE_NORM_TOLERANCE); one from a message by
ros.conversions, against MESSAGE_NORM_TOLERANCE, with the reason codes of /diagnostics.
"""

import math

NS_PER_S = 1_000_000_000
# eye_in_hand: the sensor rides on the link, the answer is T_link_sensor; eye_to_hand: the
# sensor is fixed in the cell, the answer is T_base_sensor.
SETUPS = ('eye_in_hand', 'eye_to_hand')
# The result's (parent, child) frames when nothing names them: the robot's flange or its base.
DEFAULT_FRAMES = {'eye_in_hand': ('tool0', 'camera'), 'eye_to_hand': ('base_link', 'camera')}
# A pose message's quaternion is computed in floating point by a program: a norm off by more
# than this is a bug upstream, not rounding (within it, the quaternion is renormalised).
MESSAGE_NORM_TOLERANCE = 1e-3
# A file's quaternion may have been rounded to a few digits (by hand or a spreadsheet).
FILE_NORM_TOLERANCE = 1e-2
# The words every warning ends with (or holds) whose estimate must not be used: the result is
# then not `usable` (core.calibration.CalibrationResult), and the node does not broadcast it.
DO_NOT_USE = 'do not use this estimate'
# A position farther than this (metres) from its frame's origin is a unit or typing error
# (millimetres for metres, a misplaced decimal point), not a robot cell.
MAX_POSITION_M = 1000.0


def shown(text, limit=40):
    """Return `text` (a value from the input) for a message, cut to `limit` characters."""
    text = str(text)
    return text if len(text) <= limit else text[:limit - 3] + '...'


def ns_from_s(seconds):
    """Return `seconds` (float) as integer nanoseconds, rounded to the nearest."""
    return int(round(seconds * NS_PER_S))


def plain_number(text, kind=float):
    """
    Return the number (a `kind`: float or int) a text writes; ValueError when it is not plain.

    float() and int() also read 0_455 as 455 and digits of other scripts ('\u0663' as 3): no
    program that writes numbers writes those, a hand-edited cell or option does by mistake.
    """
    if '_' in text or not text.isascii():
        raise ValueError(text)
    return kind(text)


def position_problem(position):
    """
    Say why a position read from a file (a coordinate, or the three) is not one, or None.

    A coordinate beyond MAX_POSITION_M is a unit or typing error, not a robot cell.
    """
    scalar = isinstance(position, (int, float))
    values = [position] if scalar else list(position)
    if all(abs(v) <= MAX_POSITION_M for v in values):
        return None
    text = f'{position:g}' if scalar else str(values)
    return (f'{text} m is not a position in a robot cell (at most {MAX_POSITION_M:g} m from the '
            'origin; positions are in metres)')


def quaternion_norm_problem(xyzw, tolerance):
    """
    Say why the quaternion `xyzw` (4 numbers, any order) is not a unit quaternion, or None.

    The text is 'the quaternion has norm N, not 1 (tolerance T)'; callers put the field in
    front of it.  NaN and inf give a norm that is not within the tolerance.
    """
    norm = math.sqrt(sum(float(v) * float(v) for v in xyzw))
    if abs(norm - 1.0) <= tolerance:
        return None
    digits = 6 if abs(norm - 1.0) < 0.01 else 4   # (1.0011 is not '1.001' at tolerance 0.001)
    return f'the quaternion has norm {norm:.{digits}g}, not 1 (tolerance {tolerance:g})'
