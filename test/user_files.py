"""
The user's own ROS directories, watched over a test session: the tests must never touch them.

watched_dirs() names where the package and rcl write when nothing points them elsewhere (the
samples journal and result under ~/.ros/quatcal, rcl's log files under $ROS_LOG_DIR,
$ROS_HOME/log or ~/.ros/log, easy_handeye2 exports under ~/.ros2).  snapshot() lists each one's
entries with kind, size and modification time; changes() says what differs between two.
"""

import os
from pathlib import Path
import pwd


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
    lines = []
    for folder in sorted(before):
        old, new = before[folder], after[folder]
        if old is None and new is not None:
            lines.append(f'{folder}: created (now holds {sorted(new)})')
        elif old is not None and new is None:
            lines.append(f'{folder}: removed')
        elif old is not None:
            for name in sorted(set(old) | set(new)):
                path = folder / name
                if name not in old:
                    lines.append(f'{path}: created')
                elif name not in new:
                    lines.append(f'{path}: removed (moved aside?)')
                elif old[name][1] != new[name][1]:
                    lines.append(f'{path}: modified (size {old[name][1]} -> {new[name][1]})')
                elif old[name] != new[name]:
                    lines.append(f'{path}: modified (same size, new mtime)')
    return lines
