"""
The samples CSV of DESIGN.md contract 2: one still sample per row.

    stamp,link_x,link_y,link_z,link_qx,link_qy,link_qz,link_qw,
    sensor_x,sensor_y,sensor_z,sensor_qx,sensor_qy,sensor_qz,sensor_qw

stamp in seconds, positions in metres, quaternions (x, y, z, w) as in ROS (converted to the
core's (w, x, y, z) here, by column name).  Lines starting with '#' before the header row are
comments (the samples journal of the live node, journal.py, starts with one, so `solve` reads
it as it is).  Errors name the file, the row (line number in the file) and the field.
"""

import csv
import io
import math

from quatcal_ros.core.pose import Pose, Sample
from quatcal_ros.core.quaternion import wxyz_from_xyzw
from quatcal_ros.core.units import FILE_NORM_TOLERANCE, MAX_POSITION_M, quaternion_norm_problem

COLUMNS = ('stamp',
           'link_x', 'link_y', 'link_z', 'link_qx', 'link_qy', 'link_qz', 'link_qw',
           'sensor_x', 'sensor_y', 'sensor_z', 'sensor_qx', 'sensor_qy', 'sensor_qz', 'sensor_qw')
# Stamps are integer nanoseconds in the core (int64, as rosbag2 stores them).
MAX_STAMP_S = 2 ** 63 / 1e9


class BadInputError(ValueError):
    """Input that cannot be used; the message names the file, row and field."""


def read_samples(path):
    """Read samples (list of pose.Sample) from a samples CSV file; raise BadInputError."""
    try:
        # utf-8-sig: the byte-order mark that spreadsheet programs write is not a column name.
        with open(path, newline='', encoding='utf-8-sig') as stream:
            return parse_samples(stream, str(path))
    except OSError as error:
        raise BadInputError(f'{path}: cannot read: {error.strerror}') from None
    except UnicodeDecodeError:
        raise BadInputError(f'{path}: not a text file (UTF-8 expected)') from None


def parse_samples(stream, name='<samples>'):
    """Parse samples from an open text stream of the samples CSV format."""
    reader = csv.reader(stream)
    try:
        return _parse_rows(reader, name)
    except csv.Error as error:   # a field over the csv module's size limit, ...
        raise BadInputError(f'{name}, row {reader.line_num}: not a CSV row: {error}') from None


def _parse_rows(reader, name):
    header = next(reader, None)
    while header is not None and header and header[0].lstrip().startswith('#'):
        header = next(reader, None)   # a comment line before the header row
    if header is None:
        raise BadInputError(f'{name}: empty file: expected the header row {",".join(COLUMNS)}')
    header = [column.strip() for column in header]
    missing = [column for column in COLUMNS if column not in header]
    if missing:
        raise BadInputError(f'{name}, row 1 (header): missing column(s) {", ".join(missing)}; '
                            f'expected {",".join(COLUMNS)}')
    index = {column: header.index(column) for column in COLUMNS}
    samples = []
    for row in reader:
        if not row or all(not cell.strip() for cell in row):
            continue
        samples.append(_sample_from_row(row, index, name, reader.line_num))
    return samples


def _sample_from_row(row, index, name, line):
    values = {}
    for column, i in index.items():
        where = f'{name}, row {line}, field {column}'
        if i >= len(row):
            raise BadInputError(f'{where}: missing (the row has {len(row)} fields)')
        try:
            if '_' in row[i]:   # float() reads 0_455 as 455
                raise ValueError(row[i])
            value = float(row[i])
        except ValueError:
            raise BadInputError(f'{where}: {row[i].strip()!r} is not a number') from None
        if not math.isfinite(value):
            raise BadInputError(f'{where}: {row[i].strip()} is not a finite number')
        if column[-2:] in ('_x', '_y', '_z') and abs(value) > MAX_POSITION_M:
            raise BadInputError(f'{where}: {value:g} m is not a position in a robot cell (at '
                                f'most {MAX_POSITION_M:g} m from the origin; positions are in '
                                'metres)')
        values[column] = value
    if not abs(values['stamp']) < MAX_STAMP_S:
        raise BadInputError(f'{name}, row {line}, field stamp: {values["stamp"]:g} s is out of '
                            f'range (seconds, at most {MAX_STAMP_S:.3g} in magnitude)')
    return Sample(
        stamp_ns=int(round(values['stamp'] * 1e9)),
        link=_pose(values, 'link', name, line),
        sensor=_pose(values, 'sensor', name, line))


def _pose(values, prefix, name, line):
    xyzw = [values[f'{prefix}_q{axis}'] for axis in 'xyzw']
    problem = quaternion_norm_problem(xyzw, FILE_NORM_TOLERANCE)
    if problem:
        raise BadInputError(f'{name}, row {line}, fields {prefix}_qx..{prefix}_qw: {problem}; '
                            'quaternions are x, y, z, w')
    position = [values[f'{prefix}_{axis}'] for axis in 'xyz']
    return Pose.create(position, wxyz_from_xyzw(xyzw))


def format_samples(samples, header=True):
    """
    Format `samples` (list of pose.Sample) as samples CSV text, full float precision.

    header=False gives the rows only (one line per sample, each ending with a newline).
    """
    out = io.StringIO()
    writer = csv.writer(out, lineterminator='\n')
    if header:
        writer.writerow(COLUMNS)
    for s in samples:
        row = [f'{s.stamp_ns / 1e9:.9f}']
        for pose in (s.link, s.sensor):
            w, x, y, z = pose.quaternion
            row += [repr(float(v)) for v in (*pose.position, x, y, z, w)]
        writer.writerow(row)
    return out.getvalue()
