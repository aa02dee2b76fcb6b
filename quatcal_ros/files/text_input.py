"""
The user's text files: one error for input that cannot be used, and one way to read them.

Every reader of a user's file (samples CSV, YAML, robot poses of an image dataset) opens it
with `open_text`, so a missing file, a directory or a binary file gives the same clear error
naming the file, wherever it is read; its CSV rows come from `csv_rows` (its numbers written as
text: units.plain_number).
"""

from contextlib import contextmanager
import csv
import difflib
import io

# The most text a whole-file reader takes, and the largest journal (some 600,000 samples): far
# above any samples, result, camera or board file.
MAX_TEXT_CHARACTERS = 256 * 1024 * 1024
# A name this like a known one (difflib's ratio) and within TYPO_LENGTH characters of its
# length is its typo: still_windw_s 0.96, link_w for link_qw 0.92, sensor_cov_y_x for
# sensor_cov_x_y 0.86, Stamp 0.8. Not another program's name: map_frame for marker_frame 0.76,
# base_frame_id for base_frame 0.87 but 3 longer (a launch file's global parameters).
TYPO_RATIO = 0.8
TYPO_LENGTH = 2


def typo_of(name, names):
    """Return the name of `names` that `name` looks like a misspelling of, or None."""
    close = [known for known in difflib.get_close_matches(name, names, 3, TYPO_RATIO)
             if abs(len(known) - len(name)) <= TYPO_LENGTH]
    return close[0] if close else None


class BadInputError(ValueError):
    """Input that cannot be used; the message names the file, row and field."""


@contextmanager
def open_text(path, encoding='utf-8', newline=None):
    """
    Open a text file for reading; BadInputError names it when it cannot be read.

    Unreadable (missing, a directory, no permission) or not UTF-8 text, also when the bad
    bytes are met while the caller reads it. utf-8-sig takes a spreadsheet's byte-order mark.
    """
    try:
        with open(path, encoding=encoding, newline=newline) as stream:
            yield stream
    except OSError as error:
        raise BadInputError(f'{path}: cannot read: {error.strerror}') from None
    except UnicodeDecodeError:
        raise BadInputError(f'{path}: not a text file (UTF-8 expected)') from None


def read_text(path, limit=None):
    """
    Return the text of the UTF-8 file `path`, read once (open_text's errors).

    Without a leading byte-order mark (spreadsheets and some editors write one, in any file).
    BadInputError when it holds more than `limit` characters: read that far and no further,
    so a device such as /dev/zero cannot fill the memory. Read once, a pipe (/dev/stdin)
    reads like a file. limit: MAX_TEXT_CHARACTERS unless given.
    """
    limit = MAX_TEXT_CHARACTERS if limit is None else limit
    with open_text(path, 'utf-8-sig') as stream:
        text = stream.read(limit + 1)
    if len(text) > limit:
        raise BadInputError(f'{path}: larger than {limit // (1024 * 1024)} MiB: not a file this '
                            'tool reads (samples, results, camera and board files)')
    return text


def csv_rows(text, name):
    """
    Yield (row number in the file, cells) of CSV text; BadInputError names the row it cannot read.

    A quote (") opens a field that runs to the next quote, over the ends of lines: a stray one
    in a note swallowed the rows after it without a word, and an error in the swallowed text
    named the row where the field ended. A field that holds a line as long as a row (as many
    commas as the first row, less one) is refused, named by the row where it began; a quoted
    note written over two lines, as a spreadsheet writes one, is a field as CSV has it.
    """
    reader = csv.reader(io.StringIO(text, newline=''))
    first, width = 1, None   # the row the next record starts on; the first row's commas
    try:
        for cells in reader:
            if width is None and any(cell.strip() for cell in cells):
                width = len(cells) - 1
            if width and any(line.count(',') >= width - 1 for cell in cells
                             if '\n' in cell or '\r' in cell
                             for line in cell.splitlines()[1:]):
                raise BadInputError(
                    f'{name}, row {first}: a quote (") opens a field that takes in the rows '
                    f'after it, up to row {reader.line_num}: remove the quote, or close it on '
                    'its row')
            yield first, cells
            first = reader.line_num + 1
    except csv.Error as error:   # a field over the csv module's size limit, ...
        raise BadInputError(f'{name}, row {first}: not a CSV row: {error}') from None
