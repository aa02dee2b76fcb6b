"""
The corners of each image sample, beside the samples journal: NAME.corners.jsonl.

One JSON line per sample that has corners (sensor_input:=image):

    {"stamp_ns": 1700000000500000000, "points": [[x, y, z], ...], "pixels": [[u, v], ...]}

board points in metres (board frame), pixels as detected (mean over the still window), every
number as Python writes it (exact when read back). Lines
are appended with the samples journal and fsync'd with it; on resume they are read back (a
torn last line, from a crash mid-write, is skipped); a session that starts over moves the
file aside as the journal does (NAME.previous-TIMESTAMP). The samples journal stays the
record of the poses: a sample without a line here is still a sample.
"""

import json
import os
from pathlib import Path

from quatcal_ros.files.journal import move_aside, PREVIOUS


def corners_path(samples_path):
    """Return the corners file beside the samples journal `samples_path`."""
    path = Path(samples_path)
    return path.with_name(f'{path.stem}.corners.jsonl')


def read_corners(path):
    """Return ([(stamp_ns, points, pixels)], lines skipped) of a corners file."""
    rows, skipped, _ = _read(path)
    return rows, skipped


def _read(path):
    """Return (rows, lines skipped, bytes up to the end of the last readable line)."""
    rows, skipped, intact, offset = [], 0, 0, 0
    with open(path, 'rb') as file:
        for line in file:
            offset += len(line)
            try:
                item = json.loads(line)
                rows.append((int(item['stamp_ns']), item['points'], item['pixels']))
                intact = offset   # a whole record (its newline, if lost, is added back)
            except (ValueError, KeyError, TypeError):
                skipped += 1
    return rows, skipped, intact


def _ends_with_newline(path):
    with open(path, 'rb') as file:
        file.seek(-1, os.SEEK_END)
        return file.read(1) == b'\n'


class CornersFile:
    """The appendable corners file of a session (module docstring)."""

    def __init__(self, path, resume):
        """
        Open the file at `path`; with resume, `restored` holds the rows read back.

        Without resume an existing file is moved aside. `messages` are (level, text) to log.
        :raises OSError: when the file cannot be opened for appending.
        """
        self.path = Path(path)
        self.restored, self.messages = [], []
        if self.path.exists():
            if resume:
                self.restored, skipped, intact = _read(self.path)
                if skipped:
                    self.messages.append(('warning', f'{self.path}: {skipped} unreadable '
                                                     'line(s) skipped (a torn write?)'))
                size = self.path.stat().st_size
                if intact < size:   # cut a torn tail before appending
                    os.truncate(self.path, intact)
                if intact and not _ends_with_newline(self.path):
                    with open(self.path, 'a', encoding='utf-8') as file:
                        file.write('\n')   # a last record whose newline was lost
            else:
                moved = move_aside(self.path, PREVIOUS)
                self.messages.append(('info', f'{self.path} of an earlier session moved to '
                                              f'{moved}'))
        self._file = open(self.path, 'a', encoding='utf-8')
        self._unsynced = False

    def append(self, stamp_ns, points, pixels):
        """Write one sample's corners (in the file; fsync'd by sync)."""
        self._file.write(json.dumps({'stamp_ns': int(stamp_ns), 'points': points.tolist(),
                                     'pixels': pixels.tolist()}) + '\n')
        self._file.flush()
        self._unsynced = True

    def sync(self):
        """Fsync what append wrote."""
        if self._unsynced:
            os.fsync(self._file.fileno())
            self._unsynced = False

    def restart(self):
        """Move the file aside (when it holds any line) and start an empty one (~/reset)."""
        self._file.close()
        if self.path.exists() and self.path.stat().st_size:
            move_aside(self.path, PREVIOUS)
        self._file = open(self.path, 'w', encoding='utf-8')
        self._unsynced = False

    def close(self):
        """Fsync and close."""
        if not self._file.closed:
            self.sync()
            self._file.close()
