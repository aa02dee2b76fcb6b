"""
The samples journal: every captured sample on disk the moment it is taken, for resuming.

The journal is the samples CSV of DESIGN.md contract 2 (samples_csv) preceded by one comment
line that says what the file is and how its samples were taken:

    # quatcal_ros samples journal v1 setup=eye_in_hand link_frame=tool0 sensor_frame=camera ...
    stamp,link_x,link_y,link_z,link_qx,link_qy,link_qz,link_qw,sensor_x,...,sensor_qw
    1700000001.500000000,0.41,...

so `python -m quatcal_ros solve JOURNAL` reads it as it is, with the node's setup and
invert_sensor (the first line goes on: `invert_sensor=false`, or true; journals of earlier
versions leave it out) and, with TF input, where the mounting joins the TF tree
(`static_chain=camera_link,x,y,z,qx,qy,qz,qw` when the sensor frame hangs from a static
parent: JournalHeader) and the sensor time offsets its samples were paired with
(`sensor_time_offset_s=0.0`, or `0.0,-0.03` after a change that kept the samples).
Header values are percent-encoded (urllib.parse.quote) when they hold anything but letters,
digits and _/.:-.

Crash safety: the two header lines are written with persistence.atomic_write_text (temporary
file, fsync, rename), so a journal either exists whole or not at all.  Each sample is then
appended as one line with a single write and an fsync before the caller reports it captured
(the live node publishes the estimate between the two: `append(sample, sync=False)`, `sync()`),
so a crash (even SIGKILL or a power cut) loses at most the line being written.  Reading
tolerates exactly that: a last line without its end of line, or a last line with too few
fields, is an interrupted write and is dropped with a notice.  Anything else that does not
read (a bad row in the middle, a wrong first line, another format, a newer version) makes the
file corrupt or foreign: `start` reports it and moves it aside as NAME.corrupt-YYYYmmdd-HHMMSS
beside it.  A valid journal that is not resumed is moved aside as NAME.previous-YYYYmmdd-HHMMSS.
Nothing here deletes or overwrites a file that holds samples.

Only the paths given are touched: the journal, files beside it (the moved-aside ones, the
temporary file of the atomic write, and `.NAME.lock`, which a running journal holds locked with
flock so that two nodes configured with the same samples_file do not write into one journal,
and removes as it lets go).
The file is data: it is parsed as numbers, never evaluated.  No rclpy here.
"""

from dataclasses import dataclass, field, replace
import errno
import math
import os
from pathlib import Path
import time
from urllib.parse import quote, unquote

from quatcal_ros.core.units import DEFAULT_FRAMES, MESSAGE_NORM_TOLERANCE, plain_number, \
    position_problem, quaternion_norm_problem, SETUPS, shown
from quatcal_ros.files.persistence import atomic_write_text
from quatcal_ros.files.samples_csv import COLUMNS, format_samples, header_columns, parse_samples
from quatcal_ros.files.text_input import BadInputError, MAX_TEXT_CHARACTERS

try:   # POSIX; elsewhere journals are not locked
    import fcntl
except ImportError:   # pragma: no cover
    fcntl = None

MAGIC = '# quatcal_ros samples journal'
VERSION = 1
HEADER_KEYS = ('setup', 'link_frame', 'sensor_frame')
# Keys a header may leave out (journals of earlier versions): invert_sensor, true or false;
# static_chain, the static chain above the sensor frame with TF input; sensor_time_offset_s,
# the offsets (s) the samples were paired with (JournalHeader).
OPTIONAL_KEYS = ('invert_sensor', 'static_chain', 'sensor_time_offset_s')
BOOLEANS = {'true': True, 'false': False}
# The robot base of eye-to-hand journals of earlier versions when link_frame was not set.
LEGACY_BASE_FRAME = DEFAULT_FRAMES['eye_in_hand'][0]
SAFE_CHARACTERS = '/_.:-'
CORRUPT = 'corrupt'     # tag of a moved-aside file that is corrupt or foreign
PREVIOUS = 'previous'   # tag of a moved-aside journal of an earlier session
# A file this large cannot be a journal of one calibration (a sample is ~400 bytes).
MAX_BYTES = MAX_TEXT_CHARACTERS


class JournalError(ValueError):
    """A file that is not a readable samples journal (corrupt or foreign); says why."""


class JournalRefused(ValueError):
    """The journal cannot be used as asked (in use, other setup, not a file); says why."""


def boolean_text(value):
    """Return a header's word for a truth value (a missing one counts as false): true, false."""
    return 'true' if value else 'false'


@dataclass(frozen=True)
class JournalHeader:
    """
    How the samples of a journal were taken: the setup, the frames, the sensor's convention.

    The samples are the poses as received, so invert_sensor (None: not recorded) says how to
    solve them, not what they are: a session resumed with another value goes on.
    static_chain: with TF input, where the sensor frame already hangs in the TF tree, the top
    of its static subtree and the static transform from it to the sensor frame, (root, (x, y,
    z, qx, qy, qz, qw)), or None (stream.tf_joint.static_chain): the mounting's joint goes
    there. sensor_time_offsets: the sensor_time_offset_s values (s) the samples were paired
    with, each once in the order first used, or None (not recorded: an earlier version's).
    None of these three is compared when resuming (start warns of other offsets).
    """

    setup: str
    link_frame: str
    sensor_frame: str
    invert_sensor: bool = None
    static_chain: tuple = None
    sensor_time_offsets: tuple = None

    def paired_with(self, offset_s, kept=True):
        """
        Return this header for new samples paired with the sensor time offset `offset_s`.

        kept: whether the journal's samples stay (their offsets stay listed: unknown stays
        None); else the samples start anew, all paired with offset_s.
        """
        offsets = (offset_s,)
        if kept:
            known = self.sensor_time_offsets
            offsets = None if known is None else known + (offsets if offset_s not in known
                                                          else ())
        return replace(self, sensor_time_offsets=offsets)

    def line(self):
        """Return the first line of the journal (without its end of line)."""
        values = [f'{key}={quote(getattr(self, key), safe=SAFE_CHARACTERS)}'
                  for key in HEADER_KEYS]
        if self.invert_sensor is not None:
            values.append(f'invert_sensor={boolean_text(self.invert_sensor)}')
        if self.static_chain is not None:
            root, numbers = self.static_chain
            values.append(f'static_chain={quote(root, safe=SAFE_CHARACTERS)},'
                          + ','.join(repr(float(number)) for number in numbers))
        if self.sensor_time_offsets is not None:
            values.append('sensor_time_offset_s='
                          + ','.join(repr(float(offset)) for offset in self.sensor_time_offsets))
        return f'{MAGIC} v{VERSION} {" ".join(values)}'

    @staticmethod
    def parse(line, name='<journal>'):
        """
        Read a header line; raise JournalError when it is not a version-1 journal header.

        :param line: the first line of the file (without its end of line).
        :param name: the file name, for messages.
        """
        words = line[len(MAGIC) + 1:].split() if line.startswith(MAGIC + ' ') else []
        if not words:
            raise JournalError(
                f'{name}: not a quatcal_ros samples journal (its first line is '
                f'{shown(line, 80)!r}, expected {MAGIC!r} then its version, v{VERSION}, and '
                'its settings)')
        version, *items = words
        if version != f'v{VERSION}':
            raise JournalError(
                f'{name}: samples journal version {version!r}; this quatcal_ros reads '
                f'v{VERSION} only')
        values = {}
        for item in items:
            key, sep, value = item.partition('=')
            if not sep or key not in HEADER_KEYS + OPTIONAL_KEYS or key in values:
                raise JournalError(f'{name}, row 1: unexpected {item!r} in the journal header')
            values[key] = value if key in ('static_chain', 'sensor_time_offset_s') \
                else unquote(value)
        if 'invert_sensor' in values:
            invert = BOOLEANS.get(values['invert_sensor'])
            if invert is None:
                raise JournalError(f'{name}, row 1: invert_sensor='
                                   f'{shown(values["invert_sensor"])!r} in the journal header '
                                   'is not true or false')
            values['invert_sensor'] = invert
        missing = [key for key in HEADER_KEYS if not values.get(key)]
        if missing:
            raise JournalError(
                f'{name}, row 1: the journal header lacks {", ".join(missing)}')
        if values['setup'] not in SETUPS:
            raise JournalError(f'{name}, row 1: setup={shown(values["setup"])!r} in the journal '
                               f'header is not one of {", ".join(SETUPS)}')
        if 'static_chain' in values:
            values['static_chain'] = _static_chain(values['static_chain'],
                                                   values['sensor_frame'], name)
        if 'sensor_time_offset_s' in values:
            values['sensor_time_offsets'] = _offsets(values.pop('sensor_time_offset_s'), name)
        return JournalHeader(**values)

    def differences(self, other, origins=None):
        """
        Return 'key: mine vs other' for each of HEADER_KEYS that differs from `other`.

        Not invert_sensor: the samples are the same poses either way (the class docstring).
        origins: {key: why other's value is not the parameter as given} (Settings'
        result_frame_origins), said after it.
        """
        origins = origins or {}
        return [f'{key} {getattr(self, key)!r} (parameters: {getattr(other, key)!r}'
                f'{", " + origins[key] if key in origins else ""})'
                for key in HEADER_KEYS if getattr(self, key) != getattr(other, key)]


def _static_chain(text, sensor_frame, name):
    """Return a header's static_chain=ROOT,x,y,z,qx,qy,qz,qw as JournalHeader holds it."""
    root, *numbers = text.split(',')
    root = unquote(root)
    problem = _chain_problem(root, numbers, sensor_frame)
    if problem:
        raise JournalError(f'{name}, row 1: static_chain={shown(text)!r} in the journal header: '
                           f'{problem} (expected FRAME,x,y,z,qx,qy,qz,qw: the top of the '
                           'static chain above the sensor frame and the transform from it)')
    return root, tuple(float(number) for number in numbers)


def _offsets(text, name):
    """Return a header's sensor_time_offset_s=S[,S...] as JournalHeader holds it."""
    values = _finite_numbers(text.split(','))
    if values is None:
        raise JournalError(f'{name}, row 1: sensor_time_offset_s={shown(text)!r} in the '
                           'journal header: expected seconds, finite numbers separated by '
                           'commas')
    return values


def _finite_numbers(texts):
    """Return `texts` as a tuple of finite floats, or None when one is not a plain number."""
    try:   # (float() reads 1_0 as 10: refused, as in the samples)
        values = tuple(plain_number(text) for text in texts)
    except ValueError:
        return None
    if not all(map(math.isfinite, values)):
        return None
    return values


def _chain_problem(root, numbers, sensor_frame):
    """Say what is wrong with a static_chain's frame and numbers, or ''."""
    if not root.lstrip('/'):
        return 'no frame'
    if root.lstrip('/') == sensor_frame.lstrip('/'):   # (leading slashes aside, as TF's)
        return f'the frame is the sensor frame {sensor_frame} itself'
    if len(numbers) != 7:
        return f'{len(numbers)} numbers, 7 expected'
    values = _finite_numbers(numbers)
    if values is None:
        return 'not 7 finite numbers'
    return (position_problem(values[:3])
            or quaternion_norm_problem(values[3:], MESSAGE_NORM_TOLERANCE) or '')


@dataclass(frozen=True)
class JournalContents:
    """What a journal file holds: header, samples (pose.Sample), and notices about the tail."""

    header: JournalHeader
    samples: list
    notices: list = field(default_factory=list)
    intact_bytes: int = 0       # length of the part that reads (the rest is a torn last line)
    size_bytes: int = 0
    covariance_columns: bool = True   # False: an earlier version's column row, without them


def read_journal(path):
    """
    Read a samples journal, tolerating a torn last line (see the module docstring).

    :return: JournalContents.
    :raises FileNotFoundError: when there is no file.
    :raises JournalError: when the file is corrupt or foreign (the message says where and why).
    :raises OSError: when it cannot be read.
    """
    path = Path(path).expanduser()
    name = str(path)
    if not path.is_file():
        if path.exists():
            raise JournalError(f'{name}: not a regular file')
        raise FileNotFoundError(errno.ENOENT, 'no samples journal', name)
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise JournalError(f'{name}: {size} bytes, far too large for a samples journal')
    data = path.read_bytes()
    if not data:
        raise JournalError(f'{name}: empty file (a journal starts with {MAGIC!r})')
    end = data.rfind(b'\n') + 1
    intact, tail = data[:end], data[end:]
    try:
        text = intact.decode('utf-8-sig')   # (a byte-order mark an editor added)
    except UnicodeDecodeError as error:
        raise JournalError(f'{name}: not a text file (byte {error.start} is not UTF-8)') \
            from None
    lines = text.split('\n')[:-1]     # the text ends with a newline (or is empty)
    if len(lines) < 2:
        first = lines[0] if lines else data[:80].decode('utf-8', 'replace')
        JournalHeader.parse(first.rstrip('\r'), name)   # a foreign file says so here
        raise JournalError(f'{name}: the journal ends before its column row')
    header = JournalHeader.parse(lines[0].rstrip('\r'), name)
    complete, notices = complete_lines(text, name, len(tail))
    end -= len(text[len(complete):].encode('utf-8'))
    text = complete
    try:
        samples = parse_samples(text, name)
    except BadInputError as error:
        raise JournalError(str(error)) from None
    return JournalContents(header, samples, notices, end, size, not _earlier_columns(lines[1]))


def complete_lines(text, name, torn_bytes=0):
    """
    Return a journal's text without the line a crash interrupted, and the notices saying so.

    text: the file's text up to its last end of line; torn_bytes: the length of what follows
    it (a last line without its end of line: dropped). A last line with too few fields is an
    interrupted write too (module docstring); not a blank line or a '#' comment (added by hand:
    the samples CSV reads them as such).
    """
    notices = []
    if torn_bytes:
        notices.append(f'{name}: the last line ({torn_bytes} bytes without an end of line) was '
                       'being written when the node stopped: dropped')
    lines = text.split('\n')[:-1]
    last = lines[-1].strip() if lines else ''
    if (len(lines) > 2 and last and not last.startswith('#')
            and last.count(',') < len(COLUMNS) - 1):
        notices.append(f'{name}, row {len(lines)}: the last line has '
                       f'{lines[-1].count(",") + 1} of {len(COLUMNS)} fields, an interrupted '
                       'write: dropped')
        text = text[:len(text) - len(lines[-1]) - 1]
    return text, notices


def _earlier_columns(line):
    """
    Return whether `line` is the column row of an earlier version, without the covariances.

    As it wrote it: a file edited by hand (columns in another order, a comment) is left be.
    """
    return line.rstrip('\r') == ','.join(header_columns(False))


def aside_path(path, tag, now=None):
    """
    Return a free name NAME.TAG-YYYYmmdd-HHMMSS beside `path` (with -2, -3, ... if taken).

    :param now: seconds since the epoch (time.time() by default); local time in the name.
    """
    path = Path(path)
    stamp = time.strftime('%Y%m%d-%H%M%S', time.localtime(time.time() if now is None else now))
    candidate = path.with_name(f'{path.name}.{tag}-{stamp}')
    counter = 2
    while candidate.exists() or candidate.is_symlink():
        candidate = path.with_name(f'{path.name}.{tag}-{stamp}-{counter}')
        counter += 1
    return candidate


def move_aside(path, tag, now=None):
    """
    Rename `path` to aside_path(path, tag) without ever replacing an existing file.

    :return: the new path.
    :raises OSError: when the file cannot be renamed (it then stays where it was).
    """
    path = Path(path)
    while True:
        target = aside_path(path, tag, now)
        try:
            os.link(path, target)       # fails if target exists: never overwrites
        except FileExistsError:
            continue                    # taken meanwhile: find the next free name
        except OSError:                 # no hard links here (some file systems)
            if target.exists():
                continue
            os.rename(path, target)
            return target
        os.unlink(path)
        return target


@dataclass
class StartReport:
    """What `start` did: samples to resume and the messages to log, as (level, text)."""

    samples: list = field(default_factory=list)
    messages: list = field(default_factory=list)
    moved_to: Path = None


class Journal:
    """
    An open samples journal that appends one fsync'd line per sample.

    Made by `start` (the node's start-up policy) or `Journal.create`; `count` is the number of
    samples it holds.  Samples that could not be written (disk full) are kept and written, in
    order, before the next sample, so the file never has a gap.
    """

    def __init__(self, path, header, count=0, lock_fd=None):
        self.path = absolute(path)
        self.header = header
        self.header_written = True   # False: set_header's first line is not in the file yet
        self.count = count
        self._lock_fd = lock_fd
        self._fd = None
        self._unwritten = []
        self._unsynced = False
        self._open()

    def _open(self):
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        self._size = os.fstat(self._fd).st_size

    # --- making one -----------------------------------------------------------------------

    @staticmethod
    def create(path, header, lock_fd=None):
        """
        Write a new, empty journal at `path` (atomically; parent directories are made).

        :raises FileExistsError: when `path` exists (move it aside first).
        :raises OSError: when the file cannot be written.
        """
        _write_empty(path, header)
        return Journal(path, header, 0, lock_fd)

    # --- writing --------------------------------------------------------------------------

    @property
    def unwritten(self):
        """Return the number of samples not yet on disk (after a failed write)."""
        return len(self._unwritten)

    def append(self, sample, sync=True):
        """
        Append one sample (pose.Sample) and fsync; return when it is on disk.

        With sync=False the line is written (so it survives the process, SIGKILL included)
        but not fsync'd: call sync() to have it survive a power cut too. The live node
        publishes the new estimate in between.
        :raises OSError: when it cannot be written; the sample is kept and written before the
            next one, and any partial line is cut off first.
        """
        self._unwritten.append(format_samples([sample], header=False).encode('utf-8'))
        self.count += 1
        self.flush(sync)

    def flush(self, sync=True):
        """
        Write the samples not yet in the file (see append), fsync'd unless sync=False.

        And a first line that set_header could not write.
        """
        if self._fd is None and self._unwritten:   # a restart that failed: try it again
            if not self.path.exists():
                _write_empty(self.path, self.header)
                self.header_written = True
            self._open()
        if not self.header_written and not self.lost():
            self._write_header()
        while self._unwritten:
            data = self._unwritten[0]
            if os.fstat(self._fd).st_size != self._size:
                os.ftruncate(self._fd, self._size)   # a partial line of a failed write
            written = 0
            while written < len(data):
                written += os.write(self._fd, data[written:])
            self._unsynced = True
            self._size += len(data)
            self._unwritten.pop(0)
        if sync:
            self.sync()

    def lost(self):
        """Return whether the file was deleted or replaced since it was opened."""
        if self._fd is None:
            return False
        opened = os.fstat(self._fd)
        try:
            now = os.stat(self.path)
        except FileNotFoundError:
            return True
        same = (now.st_dev, now.st_ino) == (opened.st_dev, opened.st_ino)
        return opened.st_nlink == 0 or not same

    def rewrite(self, samples):
        """
        Write the journal anew, atomically: the header and `samples` (all of the session's).

        For a journal that was deleted or replaced while it was open (`lost`); a file put in
        its place is moved aside first, never overwritten.
        :raises OSError: when it cannot be written; the journal stays as it was.
        """
        if self.path.exists() or self.path.is_symlink():
            move_aside(self.path, PREVIOUS)
        atomic_write_text(self.path, self.header.line() + '\n'
                          + format_samples(samples, covariance_columns=True))
        self.header_written = True
        os.close(self._fd)
        self._fd = None
        self.count = len(samples)
        self._unwritten = []
        self._unsynced = False
        self._open()

    def sync(self):
        """Fsync the lines written since the last sync; raise OSError on failure."""
        if self._unsynced:
            os.fsync(self._fd)
            self._unsynced = False

    def set_header(self, header):
        """
        Take a new first line (setup or frames changed at runtime) and write it, atomically.

        The header is taken at once: a write that fails is tried again by the next flush, and
        rewrite and restart write it too. The sample lines stay byte for byte. A journal
        deleted or replaced meanwhile (`lost`) is not read (a file put in its place is not
        ours): the next append re-creates it, with this header (SamplesJournal.append).
        :raises OSError: when the file cannot be replaced (header_written stays False).
        """
        if header == self.header and self.header_written:
            return
        self.header = header
        self.rewrite_head()

    def rewrite_head(self):
        """
        Write the journal's first two lines anew (set_header's, an earlier version's columns).

        Not a journal deleted or replaced meanwhile (`lost`): the next append re-creates it.
        :raises OSError: when the file cannot be replaced (the next flush tries again).
        """
        self.header_written = False
        if self.lost():
            return
        self.flush()   # the samples not yet written, and the head

    def _write_header(self):
        """
        Write the first line anew; and an earlier version's column row, with the covariances.

        Any other second line (a column row in another order, a comment) stays as it is.
        """
        data = self.path.read_bytes()[:self._size]   # not a partial line of a failed write
        second, rest = data.decode('utf-8').split('\n', 1)[1].split('\n', 1)
        if _earlier_columns(second):
            second = ','.join(header_columns(True))
        atomic_write_text(self.path, f'{self.header.line()}\n{second}\n{rest}')
        self.header_written = True
        os.close(self._fd)
        self._open()

    def restart(self, now=None, header=None):
        """
        Start an empty journal at the same path (~/reset), with `header` if given.

        The old one, if it holds samples, is moved aside as NAME.previous-TIMESTAMP; samples
        not yet written are dropped with it (the session forgets them too).
        :return: the path the old journal was moved to, or None when it held no sample.
        :raises OSError: when the old file cannot be moved or the new one written.
        """
        os.close(self._fd)
        self._fd = None
        moved = None
        if self.count and self.path.exists():
            moved = move_aside(self.path, PREVIOUS, now)
        elif self.path.exists():
            self.path.unlink()    # no samples: nothing to keep
        self.count = 0
        self._unwritten = []
        self._unsynced = False
        self.header = header or self.header
        _write_empty(self.path, self.header)
        self.header_written = True
        self._open()
        return moved

    def close(self, unlock=True):
        """Close the file, fsync'd (and release the lock unless unlock=False)."""
        if self._fd is not None:
            try:
                self.sync()
            except OSError:
                pass   # shutting down: the lines are written, only a power cut loses them
            os.close(self._fd)
            self._fd = None
        if unlock and self._lock_fd is not None:
            release_lock(self.path, self._lock_fd)
            self._lock_fd = None


def _write_empty(path, header):
    """Write the two header lines of a new journal atomically; never replace a file."""
    path = absolute(path)
    if path.exists() or path.is_symlink():
        raise FileExistsError(errno.EEXIST, 'refusing to overwrite', str(path))
    atomic_write_text(path, f'{header.line()}\n{",".join(header_columns(True))}\n')


def absolute(path):
    """Expand ~ in `path` and make it absolute; nothing else (no variables, no globbing)."""
    return Path(path).expanduser().absolute()


def lock_path(path):
    """Return the lock file of the journal `path`: .NAME.lock beside it."""
    path = absolute(path)
    return path.with_name(f'.{path.name}.lock')


def lock(path):
    """
    Lock the journal `path` for this process (flock on lock_path(path)); return the lock fd.

    :raises JournalRefused: when another process (or node) holds it.
    :raises OSError: when the directory cannot be made or the lock file opened.
    """
    if fcntl is None:   # pragma: no cover
        return None
    lock_file = lock_path(path)
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            os.close(fd)
            if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise JournalRefused(
                    f'{absolute(path)} is in use by another running calibrator (locked through '
                    f'{lock_file}): give each node a samples_file of its own') from None
            raise
        if _same_file(fd, lock_file):
            return fd
        os.close(fd)   # its holder removed it as it let go (release_lock): lock the new one


def release_lock(path, fd):
    """Remove the lock file of the journal `path` while it is still ours, then let go."""
    if fd is None:   # pragma: no cover (no fcntl)
        return
    lock_file = lock_path(path)
    try:
        if _same_file(fd, lock_file):
            lock_file.unlink()
    except OSError:
        pass   # left behind: harmless, the next lock takes it
    os.close(fd)   # closing releases the flock


def _same_file(fd, path):
    """Return whether the open `fd` is the file at `path` (not one removed or replaced)."""
    try:
        there = os.stat(path)
    except FileNotFoundError:
        return False
    held = os.fstat(fd)
    return (held.st_dev, held.st_ino) == (there.st_dev, there.st_ino)


def start(path, header, resume, now=None, resumable=True, origins=None):
    """
    Open the journal at `path` for a node starting up; the policy of the module docstring.

    - No file: a new journal.
    - A corrupt or foreign file: reported (level 'error'), moved aside as NAME.corrupt-..., a
      new journal; nothing is resumed.
    - A journal, resume=True: its samples are returned for resuming (a torn last line is cut
      off, with a 'warning'), and new samples are appended to it.  Refused (JournalRefused)
      when its setup or frames differ from `header`, so data of two set-ups never mix.
    - A journal with samples, resume=False: moved aside as NAME.previous-... (a 'warning' that
      says where, and that resume:=true would have continued it), a new journal.

    :param path: the samples_file parameter (~ is expanded; a symbolic link is followed: the
        journal is the file it names, moved aside, re-created and locked as such, so that the
        link stays and two names of one journal share its lock).
    :param header: JournalHeader of the node's parameters.
    :param resume: the resume parameter.
    :param resumable: whether the caller can resume (the node); the offline tools' journal
        is a new one whatever is at the path, and the warning does not offer resume:=true.
    :param origins: {header key: why its value is not the parameter as given}, for the
        refusal (JournalHeader.differences).
    :return: (Journal, StartReport).
    :raises JournalRefused: in use by another process, setup or frames differ (resume), or
        the path is a directory.
    :raises OSError: when the directory or the file cannot be written.
    """
    path = Path(os.path.realpath(absolute(path)))
    if path.is_dir():
        raise JournalRefused(f'{path} is a directory; samples_file must name a file')
    if path.exists() and not path.is_file():   # a device such as /dev/null, a pipe, a socket
        raise JournalRefused(f'{path} exists and is not a regular file; samples_file must '
                             'name a regular file (it is never moved aside or replaced)')
    lock_fd = lock(path)
    try:
        return _start_locked(path, header, resume, lock_fd, now, resumable, origins)
    except BaseException:
        release_lock(path, lock_fd)
        raise


def _resumed_offsets(path, recorded, header, count):
    """
    Warn when the parameters' sensor time offset is not the one the resumed samples had.

    They keep the pairing they were taken with, as after a change at runtime. (The first line
    gains the new offset with the first sample paired with it: JournalHeader.paired_with.)
    """
    if header.sensor_time_offsets is None or recorded.sensor_time_offsets is None or not count:
        return []
    offset, recorded = header.sensor_time_offsets[-1], recorded.sensor_time_offsets
    if set(recorded) == {offset}:
        return []
    # (the value exactly, as the first line has it: a rounded one would warn again)
    same = (f', or resume with sensor_time_offset_s:={recorded[0]!r}' if len(recorded) == 1
            else '')
    return [('warning', f'{path}: its {count} samples were paired with '
                        f'sensor_time_offset_s {" then ".join(f"{s:g}" for s in recorded)} '
                        f'(its first line); {offset:g} applies to new poses only: the samples '
                        'resumed keep their pairing. Call ~/reset to take them again with '
                        f'{offset:g}{same}')]


def unnamed_base(recorded):
    """
    Return whether `recorded` is an eye-to-hand header of an earlier version's default base.

    Before they took link_frame_id or base_link, eye-to-hand sessions left link_frame at its
    default named the robot base LEGACY_BASE_FRAME (a flange's name): no frame was named.
    """
    return recorded.setup == 'eye_to_hand' and recorded.link_frame == LEGACY_BASE_FRAME


def _unnamed_base(recorded, wanted):
    """Return unnamed_base(recorded) for a resume with the header `wanted` of another base."""
    return (unnamed_base(recorded) and wanted.setup == 'eye_to_hand'
            and wanted.link_frame != LEGACY_BASE_FRAME)


def _start_locked(path, header, resume, lock_fd, now, resumable=True, origins=None):
    report = StartReport()
    try:
        contents = read_journal(path)
    except FileNotFoundError:
        if resume:
            report.messages.append(
                ('warning', f'resume:=true, but there is no samples journal at {path} yet: '
                            'nothing to resume, starting a new one'))
        else:
            report.messages.append(('info', f'captured samples are saved to {path}'))
        return Journal.create(path, header, lock_fd), report
    except JournalError as error:
        report.moved_to = move_aside(path, CORRUPT, now)
        report.messages.append(
            ('error', f'{error}; this file is corrupt or not a samples journal: moved to '
                      f'{report.moved_to}, not used{", nothing resumed" if resume else ""}; '
                      f'starting a new journal at {path}'))
        return Journal.create(path, header, lock_fd), report
    if resume:
        recorded = contents.header
        unnamed = _unnamed_base(recorded, header)
        # An earlier version's unnamed base is compared as the base the parameters name.
        differences = (replace(recorded, link_frame=header.link_frame) if unnamed
                       else recorded).differences(header, origins)
        if differences:
            raise JournalRefused(
                f'resume:=true refused: {path} was recorded with {", ".join(differences)}; '
                'resuming would mix samples of another setup or other frames. Start with the '
                "journal's values to resume it, or with resume:=false to move it aside and "
                'start over')
        for notice in contents.notices:
            report.messages.append(('warning', notice))
        if contents.intact_bytes < contents.size_bytes:
            os.truncate(path, contents.intact_bytes)   # cut the torn line before appending
        report.samples = list(contents.samples)
        report.messages.append(
            ('info', f'resumed {len(report.samples)} samples from {path}; new samples are '
                     'appended to it'))
        resumed = Journal(path, recorded, len(report.samples), lock_fd)
        if not contents.covariance_columns:   # an earlier version's: new rows would lose theirs
            resumed.rewrite_head()
            report.messages.append(
                ('info', f'{path}: the column row of an earlier version gained the covariance '
                         'columns, so that samples appended keep their covariances'))
        if bool(recorded.invert_sensor) != bool(header.invert_sensor):   # how they are solved
            resumed.set_header(replace(resumed.header, invert_sensor=header.invert_sensor))
            report.messages.append(
                ('info', f'{path} was recorded with invert_sensor '
                         f'{boolean_text(recorded.invert_sensor)}: its samples (the poses as '
                         f'received) are solved with {boolean_text(header.invert_sensor)} '
                         'from now on, and its first line says so'))
        report.messages += _resumed_offsets(path, recorded, header, len(report.samples))
        if unnamed:   # (the offsets of its samples as recorded: the parameters' are new)
            resumed.set_header(replace(
                header, sensor_time_offsets=resumed.header.sensor_time_offsets))
            report.messages.append(
                ('warning', f'{path} named the eye-to-hand robot base {LEGACY_BASE_FRAME!r}, '
                            'the flange frame earlier versions put there when link_frame was '
                            f'not set: taken as {header.link_frame!r}, and its first line '
                            'rewritten'))
        return resumed, report
    if contents.samples or contents.notices:
        report.moved_to = move_aside(path, PREVIOUS, now)
        report.messages.append(
            ('warning', f'{path} held {len(contents.samples)} samples of an earlier session: '
                        f'moved to {report.moved_to}'
                        f'{" (resume:=true would have continued it)" if resumable else ""}; '
                        'starting a new journal'))
    else:
        path.unlink()    # a journal without samples: nothing to keep
        report.messages.append(('info', f'captured samples are saved to {path}'))
    return Journal.create(path, header, lock_fd), report
