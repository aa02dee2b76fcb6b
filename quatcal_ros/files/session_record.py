"""
What a calibration session leaves behind, and the one warning that guards it.

- `SamplesJournal`: the samples journal (journal.py) with its failures kept in view: a sample
  that could not be written is an error to report until it is on disk.
- `save_result`: the result YAML, the easy_handeye2 calibration file, or both, written
  atomically; the live node's ~/save, `solve --easy-handeye2-out` and `replay --result-out`
  all write through it.
- `MoveWatch`: warns once when the newest samples show a moved marker or sensor (drift.py).

The live node and the offline replay drive these alike; they log or print the (level, text)
messages returned here.  No rclpy here.
"""

from dataclasses import dataclass, field, replace

from quatcal_ros.core import drift
from quatcal_ros.files import exports
from quatcal_ros.files import journal
from quatcal_ros.files import persistence


class SamplesJournal:
    """
    The session's samples journal, or none (samples_file ''), with its state for the status.

    `problem` says what is not saved while something is not (None when all is well).
    """

    def __init__(self, path, header, resume, resumable=True, origins=None):
        """
        Open (or create) the journal at `path`; with resume, reload its samples.

        `report` (journal.StartReport) holds the samples to resume and the messages to log;
        resumable, origins: as journal.start takes them (resumable False for the offline
        tools).
        :raises journal.JournalRefused: in use by another node, or recorded with another
            setup or frames while resume is true.
        :raises OSError: when the journal cannot be written.
        """
        self.problem = None
        self.journal, self.report = journal.start(path, header, resume,
                                                  resumable=resumable, origins=origins)

    @property
    def path(self):
        """Return the journal's absolute path."""
        return self.journal.path

    @property
    def header(self):
        """Return the journal's JournalHeader (its first line, or the one to be written)."""
        return self.journal.header

    @property
    def count(self):
        """Return the number of samples the journal holds."""
        return self.journal.count

    @property
    def saved(self):
        """Return the number of samples on disk: the first ones (the rest wait in memory)."""
        return self.journal.count - self.journal.unwritten

    def append(self, samples, session_samples=None):
        """
        Write `samples` (in the file, not yet fsync'd: see sync); return errors to log.

        session_samples: every sample of the session (the new ones last), for re-creating a
        journal that was deleted or replaced while the node ran.
        """
        messages = []
        if samples and session_samples is not None and self.journal.lost():
            lost = self.journal.count
            try:
                self.journal.rewrite(session_samples)
            except OSError as error:
                self.problem = (f'{self.path} was deleted or replaced while the node ran and '
                                f'cannot be re-created ({error}): {len(session_samples)} '
                                'samples are not saved')
                return [('error', self.problem)]
            return [('error', f'{self.path} was deleted or replaced while the node ran (it '
                              f'held {lost} samples): re-created with all '
                              f'{len(session_samples)} samples of the session')]
        for sample in samples:
            messages += self._call(self.journal.append, sample, sync=False)
        return messages

    def sync(self):
        """Fsync what append wrote; return errors to log."""
        return self._call(self.journal.sync)

    def restart(self, header=None):
        """
        Start a new journal (~/reset); return what happened to the old one, as text.

        header: the new journal's JournalHeader, if not the old one's.
        """
        try:
            moved = self.journal.restart(header=header)
        except OSError as error:
            self.problem = f'could not start a new samples journal: {error}'
            return f'; {self.problem}'
        self.problem = None
        return f'; the old samples journal was moved to {moved}' if moved else ''

    def set_header(self, header):
        """Record a runtime change of setup or frames in the first line; errors to log."""
        return self._call(self.journal.set_header, header)

    def close(self):
        """Close the journal and release its lock."""
        self.journal.close()

    def _call(self, method, *args, **kwargs):
        waiting = self.journal.unwritten
        try:
            method(*args, **kwargs)
        except OSError as error:
            reason = error.strerror or error
            unsaved = self.journal.unwritten
            if not self.journal.header_written:
                also = f', nor {unsaved} captured sample(s) saved' if unsaved else ''
                self.problem = (f'the new setup, frames or TF joint are not yet recorded in '
                                f'{self.path}{also} ({reason}): tried again with the next '
                                'sample')
            elif unsaved:
                self.problem = (
                    f'{unsaved} captured sample(s) not yet saved to '
                    f'{self.path} ({reason}): they are kept and written with the next sample')
            else:
                self.problem = (
                    f'could not fsync {self.path} ({reason}): the samples are in the file '
                    'but may not survive a power cut; tried again with the next sample')
            return [('error', self.problem)]
        if not self.journal.unwritten and self.journal.header_written:
            self.problem = None
        if waiting and not self.journal.unwritten:
            return [('info', f'the {waiting} captured sample(s) that could not be written are '
                             f'now saved to {self.path}')]
        return []


@dataclass
class Saved:
    """What save_result wrote: [(what, path)], and what it could not: [(what, target, error)]."""

    written: list = field(default_factory=list)
    failed: list = field(default_factory=list)

    @property
    def ok(self):
        """Return whether everything asked for was written."""
        return not self.failed

    def texts(self):
        """Return one sentence per file: where it was saved, or why it could not be."""
        done = [f'saved to {path}' if what == 'result' else
                f'easy_handeye2 layout saved to {path}' for what, path in self.written]
        return done + [f'could not write {"easy_handeye2_file " if what != "result" else ""}'
                       f'{target}: {error}' for what, target, error in self.failed]


def save_result(result, frames, setup, result_file=None, easy_handeye2_file=None,
                easy_handeye2_frames=None, extra=None, joint=None):
    """
    Write `result` to the files given, each atomically (the old file stays when one fails).

    :param frames: (parent, child) of the result (exports.choose_frames).
    :param result_file: the result YAML (persistence.format_result_yaml), or None.
    :param easy_handeye2_file: easy_handeye2's calibration file (exports.easy_handeye2_yaml),
        or None.
    :param easy_handeye2_frames: its other frame names {robot_base_frame, robot_effector_frame,
        tracking_marker_frame: name}, those known.
    :param extra: more top-level keys of the result YAML (the replay's source bag).
    :param joint: the result YAML's joint in the TF tree (stream.tf_joint.Joint), or None.
    """
    saved = Saved()
    parent, child = frames
    if result_file:
        _write(saved, 'result', result_file, lambda: persistence.format_result_yaml(
            result, parent, child, setup=setup, extra=extra, joint=joint))
    if easy_handeye2_file:
        _write(saved, 'easy_handeye2', easy_handeye2_file, lambda: exports.easy_handeye2_yaml(
            result, parent, child, setup=setup,
            name=exports.easy_handeye2_name(easy_handeye2_file),
            **(easy_handeye2_frames or {})))
    return saved


def _write(saved, what, target, text):
    try:
        saved.written.append((what, persistence.atomic_write_text(target, text())))
    except OSError as error:
        saved.failed.append((what, target, error))


@dataclass
class MoveWatch:
    """
    The moved-marker check over a session's samples: warns once, until reset.

    Or until the samples come back (drift.came_back: a rise that did not last was no move).
    """

    move: drift.Move = None
    checked: int = 0     # samples the check has seen
    continuous_from: list = field(default_factory=list)   # samples where continuous began
    offline: bool = False   # over a file's samples (solve, replay): no ~/reset to call

    def check(self, samples, q_z, setup, invert_sensor=False):
        """
        Look at the samples not seen yet; return (level, text) messages to log.

        A 'warning' when a move shows first; an 'info' when the samples came back.
        """
        messages = []
        if self.move is not None and drift.came_back(samples, self.move, q_z, setup,
                                                     invert_sensor):
            messages.append(('info', f'moved-marker warning withdrawn: the last '
                                     f'{drift.RECENT} samples agree with those before sample '
                                     f'{self.move.first} again; the rise from sample '
                                     f'{self.move.first} on did not last (noisier samples, '
                                     'not a move)'))
            self.move = None
        elif self.move is None:
            self.move = drift.find_move(samples, q_z, setup, invert_sensor,
                                        first=max(0, self.checked - drift.RECENT + 1))
            if self.move is not None:
                messages.append(('warning', self.warning(len(samples))))
        self.checked = len(samples)
        return messages

    def capture_continuous(self, sample_count):
        """Note that capture became continuous after `sample_count` samples."""
        self.continuous_from.append(sample_count)

    def warning(self, sample_count):
        """Return the moved-marker warning with the current sample count, or None."""
        if self.move is None:
            return None
        # a rise that starts with the first samples of continuous capture (or soon after)
        cause = [k for k in self.continuous_from
                 if k <= self.move.first < k + drift.RECENT]
        return replace(self.move, samples=sample_count - self.move.first).text(
            cause[-1] if cause else None, self.offline)

    def reset(self):
        """Forget the samples seen (~/reset)."""
        self.move, self.checked, self.continuous_from = None, 0, []
