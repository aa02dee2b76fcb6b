"""
A pose stream in a text file: one timed pose per row, as robots, trackers and SLAM tools export.

Each row is `t x y z qx qy qz qw`: seconds, metres and a unit quaternion, scalar last (the TUM
trajectory format, and the ETH hand-eye datasets'), its numbers separated by commas or by
whitespace. Lines starting with `#` are comments; a first row of names (no cell that begins
as a number does) is a header and skipped. Every row is checked as a samples CSV's
(samples_csv: finite numbers, positions within MAX_POSITION_M, the quaternion's norm), and
the stamps must increase.
"""

import re

import numpy as np
from quatcal_ros.core.units import FILE_NORM_TOLERANCE, position_problem, \
    quaternion_norm_problem
from quatcal_ros.files.samples_csv import MAX_STAMP_S, parse_numbers, stamp_ns_from_text
from quatcal_ros.files.text_input import BadInputError, read_text

COLUMNS = ('t', 'x', 'y', 'z', 'qx', 'qy', 'qz', 'qw')
_INDEX = {column: i for i, column in enumerate(COLUMNS)}
_WHITESPACE = re.compile(r'\s+')
# A cell of a header row does not begin as a number does: a first row of numbers in another
# separator ('1;0;0;...') is no header, 'time (s)', '"t"' or '%time' are.
_LIKE_A_NUMBER = re.compile(r'[-+]?(\.?[0-9]|(inf|infinity|nan)$)', re.IGNORECASE)


def read_pose_stream(path):
    """Return (stamps_ns list, positions (N, 3), quaternions (N, 4) w x y z) of a file."""
    return parse_pose_stream(read_text(path), str(path))


def parse_pose_stream(text, name='<poses>'):
    """Return read_pose_stream's arrays of a pose stream's text, read from `name`."""
    stamps, values, last = [], [], None
    header_allowed = True
    for line_number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if not stripped or stripped.startswith('#'):
            continue
        cells = ([cell.strip() for cell in stripped.split(',')] if ',' in stripped
                 else _WHITESPACE.split(stripped))
        if header_allowed and not any(_LIKE_A_NUMBER.match(cell) for cell in cells):
            header_allowed = False   # the column names
            continue
        header_allowed = False
        if len(cells) != len(COLUMNS):
            raise BadInputError(f'{name}, row {line_number}: {len(cells)} fields, expected '
                                f'{len(COLUMNS)}: {" ".join(COLUMNS)} (seconds, metres, a '
                                'quaternion x y z w)')
        row = parse_numbers(cells, _INDEX, name, line_number)
        where = f'{name}, row {line_number}'
        if not 0.0 <= row['t'] < MAX_STAMP_S:
            raise BadInputError(f'{where}, field t: {cells[0]} s is not a stamp (seconds, from '
                                '0)')
        problem = position_problem([row[axis] for axis in 'xyz'])
        if problem:
            raise BadInputError(f'{where}, fields x..z: {problem}')
        xyzw = [row[f'q{axis}'] for axis in 'xyzw']
        problem = quaternion_norm_problem(xyzw, FILE_NORM_TOLERANCE)
        if problem:
            raise BadInputError(f'{where}, fields qx..qw: {problem}; quaternions are x, y, z, w')
        stamp_ns = stamp_ns_from_text(cells[0])
        if last is not None and stamp_ns <= last[0]:
            raise BadInputError(f"{where}, field t: {cells[0]} s is not after row {last[1]}'s "
                                f'{last[2]} s: the rows must be in time order, one pose a stamp')
        last = (stamp_ns, line_number, cells[0])
        stamps.append(stamp_ns)
        values.append([row[column] for column in COLUMNS[1:]])
    if not stamps:
        raise BadInputError(f'{name}: no poses: expected rows of {" ".join(COLUMNS)}')
    values = np.array(values)
    xyzw = values[:, 3:]
    return stamps, values[:, :3], np.column_stack([xyzw[:, 3], xyzw[:, :3]]) / np.linalg.norm(
        xyzw, axis=1)[:, None]
