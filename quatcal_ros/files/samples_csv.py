"""
The samples CSV of DESIGN.md contract 2: one still sample per row.

    stamp,link_x,link_y,link_z,link_qx,link_qy,link_qz,link_qw,
    sensor_x,sensor_y,sensor_z,sensor_qx,sensor_qy,sensor_qz,sensor_qw

stamp in seconds, positions in metres, quaternions (x, y, z, w) as in ROS (converted to the
core's (w, x, y, z) here, by column name).  Lines starting with '#' before the header row are
comments (the samples journal of the live node, journal.py, starts with one, so `solve` reads
it as it is).  Errors name the file, the row (line number in the file) and the field.

Optional: the sensor pose's own covariance in 21 columns sensor_cov_A_B (A, B in x, y, z, rx,
ry, rz, the upper triangle of geometry_msgs/PoseWithCovariance's 6x6, metres and radians,
rotations about the sensor frame's axes). A row gives all 21 or none (empty or left off);
a covariance must be usable (pose.covariance_problem: positive definite, no standard
deviation below 1e-9 or above 1e6 m or rad).
"""

import csv
from decimal import Decimal, ROUND_HALF_EVEN
import io
import math
import re

import numpy as np
from quatcal_ros.core.pose import covariance_problem, Pose, Sample
from quatcal_ros.core.units import FILE_NORM_TOLERANCE, MAX_POSITION_M, NS_PER_S, \
    plain_number, position_problem, quaternion_norm_problem, shown
from quatcal_ros.files.text_input import BadInputError, csv_rows, read_text, typo_of

COLUMNS = ('stamp',
           'link_x', 'link_y', 'link_z', 'link_qx', 'link_qy', 'link_qz', 'link_qw',
           'sensor_x', 'sensor_y', 'sensor_z', 'sensor_qx', 'sensor_qy', 'sensor_qz', 'sensor_qw')
COVARIANCE_AXES = ('x', 'y', 'z', 'rx', 'ry', 'rz')   # ROS's order
COVARIANCE_ENTRIES = tuple((i, j) for i in range(6) for j in range(i, 6))
COVARIANCE_COLUMNS = tuple(f'sensor_cov_{COVARIANCE_AXES[i]}_{COVARIANCE_AXES[j]}'
                           for i, j in COVARIANCE_ENTRIES)
# Stamps are integer nanoseconds in the core (int64, as rosbag2 stores them).
MAX_STAMP_S = 2 ** 63 / 1e9


def read_samples(path):
    """Read samples (list of pose.Sample) from a samples CSV file; raise BadInputError."""
    return parse_samples(read_text(path), str(path))


def parse_samples(text, name='<samples>'):
    """Parse samples from the text of a samples CSV (text_input.read_text's)."""
    return parse_samples_and_rows(text, name)[0]


# A comment line: '#' first (after blanks). Blanked before the CSV is split: a quote in one
# would open a field that swallows the rows after it.
COMMENT_LINE = re.compile(r'^[ \t]*#[^\n]*', re.MULTILINE)


def parse_samples_and_rows(text, name='<samples>'):
    """Return parse_samples' samples and the file row of each (as the errors count them)."""
    rows = csv_rows(COMMENT_LINE.sub('', text), name)
    line, header = next(rows, (None, None))
    while header is not None and not any(cell.strip() for cell in header):
        line, header = next(rows, (None, None))   # a blank or comment line before the header
    if header is None:
        raise BadInputError(f'{name}: empty file: expected the header row {",".join(COLUMNS)}')
    header = [column.strip() for column in header]
    where = f'{name}, row {line} (header)'
    check_header(header, COLUMNS, where, COLUMNS + COVARIANCE_COLUMNS)
    index = {column: header.index(column) for column in COLUMNS}
    given = [column for column in COVARIANCE_COLUMNS if column in header]
    if given and len(given) < len(COVARIANCE_COLUMNS):
        missing = [column for column in COVARIANCE_COLUMNS if column not in header]
        raise BadInputError(f'{where}: covariance column(s) {", ".join(missing)} '
                            f'missing: give all {len(COVARIANCE_COLUMNS)} sensor_cov_* or none')
    covariance_index = [header.index(column) for column in given]
    samples, lines = [], []
    for line, row in rows:
        if not any(cell.strip() for cell in row):
            continue   # (a blank line, or a comment: a row left out by hand)
        if any(cell.strip() for cell in row[len(header):]):   # (empty ones: a trailing comma)
            raise BadInputError(f'{name}, row {line}: {len(row)} fields, the header '
                                f'has {len(header)}: a value too many, or a decimal comma?')
        sample = _sample_from_row(row, index, name, line)
        if covariance_index:
            covariance = _covariance(row, covariance_index, name, line)
            if covariance is not None:
                sample = Sample(sample.stamp_ns, sample.link,
                                Pose(sample.sensor.position, sample.sensor.quaternion,
                                     covariance))
        samples.append(sample)
        lines.append(line)
    return samples, lines


def _covariance(row, columns, name, line):
    """Return the row's sensor covariance (6x6, ROS order), or None when it gives none."""
    cells = [row[i].strip() if i < len(row) else '' for i in columns]
    if not any(cells):
        return None
    where = f'{name}, row {line}'
    covariance = np.zeros((6, 6))
    for column, cell, (i, j) in zip(COVARIANCE_COLUMNS, cells, COVARIANCE_ENTRIES):
        try:
            value = plain_number(cell)
        except ValueError:
            raise BadInputError(f'{where}, field {column}: {shown(repr(cell))} is not a number '
                                f'(give all {len(COVARIANCE_COLUMNS)} sensor_cov_* or none)') \
                from None
        if not math.isfinite(value):
            raise BadInputError(f'{where}, field {column}: {shown(cell)} is not a finite number')
        covariance[i, j] = covariance[j, i] = value
    problem = covariance_problem(covariance)
    if problem:
        raise BadInputError(f'{where}, fields sensor_cov_*: the covariance is {problem}')
    return covariance


def _sample_from_row(row, index, name, line):
    values = parse_numbers(row, index, name, line)
    if not abs(values['stamp']) < MAX_STAMP_S:
        raise BadInputError(f'{name}, row {line}, field stamp: {values["stamp"]:g} s is out of '
                            f'range (seconds, at most {MAX_STAMP_S:.3g} in magnitude)')
    return Sample(
        stamp_ns=stamp_ns_from_text(row[index['stamp']].strip()),
        link=pose_from_values(values, 'link', name, line),
        sensor=pose_from_values(values, 'sensor', name, line))


def stamp_ns_from_text(text):
    """Return the stamp `text` (seconds, a checked finite number) in nanoseconds, exactly."""
    return int((Decimal(text) * NS_PER_S).to_integral_value(ROUND_HALF_EVEN))


def stamp_text(stamp_ns):
    """Return integer nanoseconds as exact decimal seconds (a float would move them by ~100 ns)."""
    whole, part = divmod(abs(int(stamp_ns)), NS_PER_S)
    return f'{"-" if stamp_ns < 0 else ""}{whole}.{part:09d}'


def parse_numbers(row, index, name, line):
    """
    Return {column: float} of the cells `index` ({column: position}) names in a CSV row.

    Raises BadInputError naming the file, row and field for a missing cell, one that is not
    a finite number, or a position (a column ending in _x, _y, _z) beyond MAX_POSITION_M.
    """
    try:   # the usual row: every cell a plain finite number, positions in range
        values = {column: plain_number(row[i]) for column, i in index.items()}
    except (IndexError, ValueError):
        values = None
    if (values is None or not all(map(math.isfinite, values.values()))
            or any(abs(value) > MAX_POSITION_M for column, value in values.items()
                   if column[-2:] in ('_x', '_y', '_z'))):
        _check_numbers(row, index, name, line)
    return values


def _check_numbers(row, index, name, line):
    """Raise the BadInputError of parse_numbers for the first bad cell of a row."""
    for column, i in index.items():
        where = f'{name}, row {line}, field {column}'
        if i >= len(row):
            raise BadInputError(f'{where}: missing (the row has {len(row)} fields)')
        try:
            value = plain_number(row[i])
        except ValueError:
            raise BadInputError(f'{where}: {shown(repr(row[i].strip()))} is not a '
                                'number') from None
        if not math.isfinite(value):
            raise BadInputError(f'{where}: {shown(row[i].strip())} is not a finite number')
        problem = position_problem(value) if column[-2:] in ('_x', '_y', '_z') else None
        if problem:
            raise BadInputError(f'{where}: {problem}')


def pose_from_values(values, prefix, name, line):
    """Return the Pose of the columns PREFIX_x .. PREFIX_qw of parse_numbers' values."""
    xyzw = [values[f'{prefix}_q{axis}'] for axis in 'xyzw']
    problem = quaternion_norm_problem(xyzw, FILE_NORM_TOLERANCE)
    if problem:
        raise BadInputError(f'{name}, row {line}, fields {prefix}_qx..{prefix}_qw: {problem}; '
                            'quaternions are x, y, z, w')
    position = [values[f'{prefix}_{axis}'] for axis in 'xyz']
    return Pose.create(position, xyzw[3:] + xyzw[:3])


def check_header(header, required, where, known=None):
    """
    Raise BadInputError at `where` for a header without the columns needed, or ambiguous.

    Each column of `required` must be in `header`, and none of `known` (default `required`)
    in it twice. A header of one column that holds another separator says so: a
    spreadsheet's export with semicolons or tabs is the usual cause of every column missing.
    Other columns are ignored, but one whose name is close to a known one is a typo (link_w,
    sensor_cov_y_x): named, with the one meant (an optional column misspelt was lost).
    """
    known = required if known is None else known
    missing = [column for column in required if column not in header]
    typos = _typos(header, known)
    if missing:
        other = [s for s in (';', '\t', '|') if len(header) == 1 and s in header[0]]
        hint = (f' (the header is one column separated by {other[0]!r}: columns must be '
                'separated by commas)' if other else _numbers_hint(header, required))
        raise BadInputError(f'{where}: missing column(s) {", ".join(missing)}{hint}'
                            f'{"; " + typos if typos else ""}; expected {",".join(required)}')
    if typos:
        raise BadInputError(f'{where}: {typos}')
    twice = [column for column in known if header.count(column) > 1]
    if twice:
        raise BadInputError(f'{where}: column(s) {", ".join(twice)} more than once: which '
                            'one holds the value?')


def _typos(header, known):
    """Say which columns of `header` look like misspelt `known` ones it lacks, or ''."""
    absent = [column for column in known if column not in header]
    close = {column: typo_of(column, absent)
             for column in header if column and column not in known}
    said = [f'{column} (did you mean {meant}?)' for column, meant in close.items() if meant]
    return f'unknown column(s) {", ".join(said)}' if said else ''


def _numbers_hint(header, required):
    """Say so when the header row is numbers (a file without one), else ''."""
    try:
        [float(cell) for cell in header]
    except ValueError:
        return ''
    stream = (', and 8 a row are one pose stream (a stamp, a position, a quaternion), not '
              'samples of a link and a sensor pose: give two pose streams to replay as topics '
              'of a bag' if len(header) == 8 and required == COLUMNS else '')
    return f' (the first row is {len(header)} numbers, not column names{stream})'


def header_columns(covariance):
    """Return the header's columns, with the covariance columns when `covariance`."""
    return COLUMNS + (COVARIANCE_COLUMNS if covariance else ())


def format_samples(samples, header=True, covariance_columns=None):
    """
    Format `samples` (list of pose.Sample) as samples CSV text, full float precision.

    header=False gives the rows only (one line per sample, each ending with a newline). The
    covariance columns are in the header when `covariance_columns`, or (None) when a sample
    has a covariance; a row has them only when its sample does.
    """
    out = io.StringIO()
    writer = csv.writer(out, lineterminator='\n')
    if covariance_columns is None:
        covariance_columns = any(s.sensor.covariance is not None for s in samples)
    if header:
        writer.writerow(header_columns(covariance_columns))
    for s in samples:
        row = [stamp_text(s.stamp_ns)]
        for pose in (s.link, s.sensor):
            w, x, y, z = pose.quaternion
            row += [repr(float(v)) for v in (*pose.position, x, y, z, w)]
        if s.sensor.covariance is not None:
            row += [repr(float(s.sensor.covariance[i, j])) for i, j in COVARIANCE_ENTRIES]
        writer.writerow(row)
    return out.getvalue()
