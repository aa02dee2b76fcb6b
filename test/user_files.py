"""
The user's own ROS directories, watched over a test session: the tests must never touch them.

watched_dirs() names where the package and rcl write when nothing points them elsewhere (the
samples journal and result under ~/.ros/quatcal, rcl's log files under $ROS_LOG_DIR,
$ROS_HOME/log or ~/.ros/log, easy_handeye2 exports under ~/.ros2).  snapshot() lists each one's
entries with kind, size and modification time; changes() says what differs between two, and
changes_of(before, after, pids) tells the changes of the test session's processes from the
rcl log files that other processes on the machine wrote meanwhile (a ROS system running beside
the tests: rcl names each process's log file after its process id).  A log file of a process the
caller did not list (a grandchild, say) counts as another's.
"""

import os
from pathlib import Path
import pwd
import re

# rcl's log file of a process: <executable>_<process id>_<milliseconds>.log
RCL_LOG_FILE = re.compile(r'_(\d+)_\d+\.log$')


def watched_dirs(environ):
    """Return the directories to watch for the user whose environment is `environ`."""
    home = Path(environ.get('HOME') or pwd.getpwuid(os.getuid()).pw_dir)
    ros_home = Path(environ.get('ROS_HOME') or home / '.ros').expanduser()
    log_dir = Path(environ.get('ROS_LOG_DIR') or ros_home / 'log').expanduser()
    dot_ros = home / '.ros'
    return sorted({dot_ros, dot_ros / 'quatcal', dot_ros / 'log', ros_home,
                   ros_home / 'quatcal', log_dir, home / '.ros2',
                   home / '.ros2' / 'easy_handeye2' / 'calibrations'})


def snapshot(dirs):
    """Return {dir: None (missing) or {entry name: (kind, size, mtime ns)}}."""
    out = {}
    for folder in dirs:
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            out[folder] = None
            continue
        listing = {}
        for entry in entries:
            info = entry.stat(follow_symlinks=False)
            kind = 'dir' if entry.is_dir(follow_symlinks=False) else 'file'
            listing[entry.name] = (kind, info.st_size, info.st_mtime_ns)
        out[folder] = listing
    return out


def changes(before, after):
    """Return one line per difference between two snapshots of the same dirs, [] if none."""
    return [line for _, line in _changes(before, after)]


def changes_of(before, after, pids):
    """
    Return `changes` split in two: (those of the processes `pids` or unknown ones, others').

    Others' are the rcl log files (and a log directory holding only such files) named after a
    process that is not in `pids`.
    """
    ours, others = [], []
    for paths, line in _changes(before, after):
        foreign = paths and all(_writer(path) not in (None, *pids) for path in paths)
        (others if foreign else ours).append(line)
    return ours, others


def _writer(path):
    """Return the process id an rcl log file's name holds, or None for any other file."""
    match = RCL_LOG_FILE.search(path.name)
    return int(match.group(1)) if match else None


def _changes(before, after):
    """Return (the changed paths, the line saying what changed) of each difference."""
    lines = []
    for folder in sorted(before):
        old, new = before[folder], after[folder]
        if old is None and new is not None:
            lines.append(([folder / name for name in new],
                          f'{folder}: created (now holds {sorted(new)})'))
        elif old is not None and new is None:
            lines.append(([], f'{folder}: removed'))
        elif old is not None:
            for name in sorted(set(old) | set(new)):
                path = folder / name
                if name not in old:
                    lines.append(([path], f'{path}: created'))
                elif name not in new:
                    lines.append(([path], f'{path}: removed (moved aside?)'))
                elif path in before and before[path] != after[path]:
                    continue   # a watched directory whose own entries say what changed
                elif path in before and old[name] != new[name]:
                    lines.append(([], f'{path}: modified (an entry created and removed since)'))
                elif path in before:
                    continue
                elif old[name][1] != new[name][1]:
                    lines.append(([path], f'{path}: modified (size {old[name][1]} -> '
                                          f'{new[name][1]})'))
                elif old[name] != new[name]:
                    lines.append(([path], f'{path}: modified (same size, new mtime)'))
    return lines
