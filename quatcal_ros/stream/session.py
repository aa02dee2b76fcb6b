"""
One calibration session: pose streams -> pairing -> capture -> Calibrator -> estimate.

The live node, the bag replay and the CSV tool all drive this one object, so they give the same
answer on the same data.  Streams come in as (header stamp in integer nanoseconds, Pose):
link poses T_base_link and sensor poses T_sensor_obj; CSV rows and resumed samples come in as
pose.Sample.  Every call returns what happened as small event objects, which the shells log
and publish (EstimateUpdated carries the new calibration.CalibrationResult):

    SampleCaptured(index, sample), EstimateUpdated(result), Rejected(what, reason),
    Notice(text)

`add_poses` takes many poses of one stream at once (an offline replay) with the result, events
included, of adding them one by one.

The estimate is made when asked for: a new sample makes it due, and `estimate()` brings it up
to date with every sample and returns its events; `result`, `state` and `last_error` tell of
the estimate of the last estimate() call.  The live node asks after every sample: one new
sample is added to the estimate incrementally, with a full robust solve every tenth sample or
so (calibration.Calibrator).  An offline replay asks once at the end: its answer is one full
solve over all its samples, that of `solve` on them.

Time that goes backwards on a stream by more than `time_jump_ns` (a bag played again, a clock
reset) starts a new timeline: the pairing buffers are cleared, the samples are kept.  The jump
is taken when a second message (of either stream) confirms it; a single message that far
behind whose stream then goes on is a stale one and is rejected ('stale_stamp'), so one
stale message does not throw away the buffers and the still being captured.  Smaller steps
back are late messages and are rejected.  After such a jump, a still sample at the stamp
(within the still window) and the link pose (within the still bands) of an earlier sample is
the same data played again (`ros2 bag play --loop`): it is not added, so that it does not
count as new evidence, and a Notice says so.  So is, on every path, a sample whose link and
sensor poses equal an earlier sample's to within REPEAT_TOLERANCE (1e-6 m, and in each
quaternion component), a quaternion's sign aside (a row copied in a file, a file appended to
itself, a copy rounded by another tool): no two measurements agree that well, and counted
twice it would shrink the reported uncertainty by sqrt(2) as if it were new evidence.
"""

import bisect
from collections import Counter
from dataclasses import dataclass, field, replace
import math

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import CalibrationOptions, Calibrator
from quatcal_ros.core.motions import motion_count
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.stream.capture import Capture, CaptureConfig, pose_change
from quatcal_ros.stream.pairing import LINK, OutOfOrderStamp, Pairer, PairingConfig, SENSOR

STATES = ('waiting for poses', 'collecting', 'estimating')
TOPICS = {LINK: 'link_pose', SENSOR: 'sensor_pose'}
_NONE_HELD = frozenset()
# After this many poses in a row could not be paired, a Notice says why.
UNPAIRED_NOTICE_AFTER = 30


@dataclass(frozen=True)
class SessionConfig:
    """Everything a session needs, as plain numbers (durations in ns on header stamps)."""

    pairing: PairingConfig = field(default_factory=PairingConfig)
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    calibration: CalibrationOptions = field(default_factory=CalibrationOptions)
    time_jump_ns: int = 500_000_000
    # Added to every sensor stamp: a known latency of the sensor's clock (time_offset.py
    # estimates it from a recording); -0.03 s for a camera stamping frames 30 ms late.
    sensor_offset_ns: int = 0

    def __post_init__(self):
        if self.time_jump_ns < 0:
            raise ValueError(f'time_jump_ns must be >= 0, not {self.time_jump_ns}')


@dataclass(frozen=True)
class SampleCaptured:
    """A sample was added to the estimator as sample number `index`."""

    index: int
    sample: object


@dataclass(frozen=True)
class EstimateUpdated:
    """A new estimate exists: publish and report `result` (calibration.CalibrationResult)."""

    result: object


@dataclass(frozen=True)
class Rejected:
    """
    Input that was not used: `what` is 'link_pose', 'sensor_pose' or 'sample'.

    `code` names the reason for counters ('non_finite', 'duplicate_stamp', 'out_of_order',
    'stale_stamp': codes of message_checks.REASONS; 'repeated': a ready sample that copies
    an earlier one, to within REPEAT_TOLERANCE); it does not take part in comparisons.  A
    sample refused by add_samples also says which it was of those given (`given`, from 0); a
    'repeated' one the number of the stored sample it repeats (`repeats`).
    """

    what: str
    reason: str
    code: str = field(default='', compare=False)
    given: int = field(default=None, compare=False)
    repeats: int = field(default=None, compare=False)


@dataclass(frozen=True)
class Notice:
    """Something the user should know (log it); `code` 'time_jump' for a clock that jumped."""

    text: str
    code: str = field(default='', compare=False)


def _finite(*poses):
    # A sum is finite exactly when every term is (short of overflow past 1e308): fast.
    return all(math.isfinite(p.position.sum() + p.quaternion.sum()) for p in poses)


# Two samples whose poses agree this closely (metres, and each quaternion component) are one
# measurement copied: no sensor repeats a reading to a micrometre, while a copy rounded to 7
# significant digits by another tool, or appended to its own file, does.
REPEAT_TOLERANCE = 1e-6


def _numbers(sample):
    """
    Return a sample's poses as 14 numbers (the positions and quaternions of both poses).

    Each quaternion with its sign chosen (q and -q are one rotation: a copy written by another
    tool may carry either).
    """
    return np.concatenate([sample.link.position, quat.canonical(sample.link.quaternion),
                           sample.sensor.position, quat.canonical(sample.sensor.quaternion)])


class _Copies:
    """The stored samples' numbers, to find the one a new sample repeats (REPEAT_TOLERANCE)."""

    def __init__(self):
        self._rows = np.empty((16, 14))
        self._count = 0

    def add(self, sample):
        """Keep a stored sample's numbers (its index: the number kept before it)."""
        if self._count == len(self._rows):
            self._rows = np.concatenate([self._rows, np.empty_like(self._rows)])
        self._rows[self._count] = _numbers(sample)
        self._count += 1

    def index_of(self, sample):
        """Return the index of the first kept sample that `sample` repeats, or None."""
        if not self._count:
            return None
        distance = np.abs(self._rows[:self._count] - _numbers(sample)).max(axis=1)
        hit = np.flatnonzero(distance <= REPEAT_TOLERANCE)
        return int(hit[0]) if len(hit) else None


def _finite_rows(positions, quaternions):
    """Return _finite of each row's pose, (n,) bool: the same sums, vectorised."""
    with np.errstate(over='ignore', invalid='ignore'):
        return np.isfinite(positions.sum(axis=1) + quaternions.sum(axis=1))


def _late_reason(error):
    """Return (text, code) of a stamp that is not newer than the previous one."""
    if error.jump_ns == 0:
        return 'same stamp as the previous message: dropped', 'duplicate_stamp'
    return (f'stamp {error.jump_ns * 1e-6:.3g} ms older than the previous message '
            '(out of order): dropped', 'out_of_order')


class Session:
    """Pairs the streams, captures samples and keeps the estimate (module docstring)."""

    def __init__(self, config=SessionConfig(), on_sample=None):
        """
        Start an empty session of `config`.

        :param on_sample: on_sample(sample) for each sample stored from the streams or the
            capture service, as it is stored (the image input keeps its corners then).
        """
        self.config = config
        self._on_sample = on_sample
        self._calibrator = Calibrator(config.calibration)
        self._start_streams()
        self._copies = _Copies()   # the numbers of each stored sample

    def _start_streams(self):
        self._pairer = Pairer(self.config.pairing)
        self._capture = Capture(self.config.capture)
        self._counts = Counter()
        self._unpaired_seen = 0
        self._unpaired_streak = 0
        self._pending = []
        self._behind = {}   # stream: (stamp_ns, pose, OutOfOrderStamp) of a jump not confirmed

    def set_capture(self, capture):
        """
        Capture with the CaptureConfig `capture` from now on; the samples and the estimate stay.

        How samples are taken does not change how those taken are solved (Capture.reconfigure).
        """
        self.config = replace(self.config, capture=capture)
        self._capture.reconfigure(capture)

    def continue_counts(self, earlier):
        """
        Take over the counts of `earlier`, the session of the same streams before new settings.

        Its messages, pairs, time jumps and refusals go on counting here; the repeat check
        after a time jump needs them (a bag looped and a setting changed between the loops
        counted the replayed stops twice).
        """
        self._counts = Counter(earlier._counts)

    # --- inputs --------------------------------------------------------------------------

    def add_link_pose(self, stamp_ns, pose):
        """Add a link pose T_base_link at header stamp stamp_ns (int); return the events."""
        return self._add_pose(LINK, stamp_ns, pose)

    def add_sensor_pose(self, stamp_ns, pose):
        """Add a sensor pose T_sensor_obj at header stamp stamp_ns (int); return the events."""
        return self._add_pose(SENSOR, stamp_ns + self.config.sensor_offset_ns, pose)

    def add_poses(self, stream, stamps_ns, positions, quaternions_wxyz):
        """
        Add many poses of stream 'link' or 'sensor', in arrival order; return the events.

        The same as add_link_pose / add_sensor_pose for each (the same events, in the same
        order), faster: in-order runs of the faster stream go to the pairer at once.
        stamps_ns: header stamps (a list of ints); positions (n, 3); quaternions_wxyz (n, 4).
        """
        events = self.pop_events()
        if stream == SENSOR:
            stamps_ns = [stamp + self.config.sensor_offset_ns for stamp in stamps_ns]
        if len(stamps_ns) == 1:   # as add_link_pose / add_sensor_pose (no arrays to scan)
            return events + self._add_pose(stream, stamps_ns[0],
                                           Pose(positions[0], quaternions_wxyz[0]))
        # Each non-finite pose goes through _add_pose, which rejects it.
        stops = np.flatnonzero(~_finite_rows(positions, quaternions_wxyz)).tolist()
        stops.append(len(stamps_ns))
        start = 0
        while start < len(stamps_ns):
            stop = stops[bisect.bisect_left(stops, start)]
            taken, pairs = (0, []) if stream in self._behind else self._pairer.add_many(
                stream, stamps_ns[start:stop], positions[start:stop],
                quaternions_wxyz[start:stop])
            if taken:
                self._counts[stream] += taken
                events += self._paired(pairs)
            else:   # out of order, or the next of a stream held behind: one by one
                pose = Pose(positions[start], quaternions_wxyz[start])
                events += self._add_pose(stream, stamps_ns[start], pose)
                taken = 1
            start += taken
        return events

    def capture(self, now_ns):
        """
        Capture a sample now from the latest still window (manual mode, or any mode).

        now_ns: the current time on the stamps' clock (the node gives its estimate of it,
        CalibratorNode.stamps_now_ns).  Returns (True, description) or (False, the reason
        for refusing); the events of a capture come with pop_events() or the next add_*()
        call.
        """
        sample, reason = self._capture.capture_now(int(now_ns))
        if sample is None:
            return False, reason
        repeated = self._repeat_of(sample)
        if repeated is not None:
            return False, self._replayed('this still', repeated)
        self._pending += self._store(sample)
        return True, f'sample {self._sample_count() - 1} captured: {reason}'

    def add_sample(self, sample):
        """Add a ready sample (pose.Sample: CSV row, resumed session); return the events."""
        events = self.pop_events()
        if not _finite(sample.link, sample.sensor):
            return events + [self._reject('sample', 'non-finite numbers in a pose',
                                          'non_finite')]
        copied = self._copy_of(sample)
        if copied is not None:
            return events + [self._repeated(0, copied)]
        return events + self._store(sample)

    def add_samples(self, samples):
        """Add many ready samples (a CSV file, a resumed session); return the events."""
        events = self.pop_events()
        good = []
        first = self._sample_count()
        for position, sample in enumerate(samples):
            if not _finite(sample.link, sample.sensor):
                events.append(replace(self._reject('sample', 'non-finite numbers in a pose',
                                                   'non_finite'), given=position))
                continue
            copied = self._copy_of(sample)
            if copied is None:
                self._copies.add(sample)
                good.append(sample)
            else:
                events.append(self._repeated(position, copied))
        self._calibrator.add_samples(good)
        if good:
            self._capture.note_sample(good[-1])   # the next still sample needs a motion first
        return events + [SampleCaptured(first + k, sample) for k, sample in enumerate(good)]

    def estimate(self):
        """
        Bring the estimate up to date with every sample; return its events.

        Those are the estimator's messages (Notice), then EstimateUpdated with the new
        estimate, if there is one; none when no sample came since the last estimate().
        """
        if not self._calibrator.due:
            return []
        events = [Notice(text) for text in self._calibrator.estimate()]
        if self._calibrator.result is not None:   # a new one
            events.append(EstimateUpdated(self._calibrator.result))
        return events

    def full_estimate(self):
        """
        Bring the estimate to the full solve of every sample; return its events.

        No events when it is that already; else the live warm-started estimate is solved
        again in full (calibration.Calibrator.solve_fully), as `solve` of the same samples.
        """
        self._calibrator.solve_fully()
        return self.estimate()

    def pop_events(self):
        """Events not yet returned (those of capture()); each event is returned once."""
        events, self._pending = self._pending, []
        return events

    def reset(self):
        """Start over: forget the streams, the samples, the estimate and the counters."""
        self._calibrator.reset()
        self._start_streams()
        self._copies = _Copies()

    # --- what the shells show ------------------------------------------------------------

    @property
    def samples(self):
        """Return the samples so far (list of pose.Sample), in the estimator's order."""
        return list(self._calibrator.samples)

    @property
    def result(self):
        """Return the calibration.CalibrationResult of the last estimate(), or None."""
        return self._calibrator.result

    @property
    def last_error(self):
        """Return why there is no estimate (the estimator's last message)."""
        return self._calibrator.last_error

    @property
    def state(self):
        """Return the state: 'waiting for poses', 'collecting' or 'estimating'."""
        if self._calibrator.result is not None:
            return STATES[2]
        if self._counts['pairs'] or self._sample_count():
            return STATES[1]
        return STATES[0]

    @property
    def counters(self):
        """
        Return the counts since the last reset.

        link_messages, sensor_messages: poses received; pairs, unpaired: sensor (slower
        stream) stamps paired or not; samples; motions: sample pairs the estimator forms;
        rejected: messages and samples not used; time_jumps: new timelines started;
        repeated_samples: samples not added because they repeat earlier ones (module doc);
        unsteady_sensor: paired poses at which the link stood still but the sensor pose
        moved beyond its still bands (auto capture); sensor_jumps: sensor poses left out of
        still samples, over twice the sensor bands for a frame or a few (a marker flip).
        """
        samples = self._sample_count()
        return {
            'link_messages': self._counts[LINK],
            'sensor_messages': self._counts[SENSOR],
            'pairs': self._counts['pairs'],
            'unpaired': self._unpaired_seen,
            'samples': samples,
            'motions': motion_count(samples, self._calibrator.options.pairs),
            'rejected': self._counts['rejected'],
            'time_jumps': self._counts['time_jumps'],
            'repeated_samples': self._counts['repeated_samples'],
            'unsteady_sensor': self._capture.unsteady_sensor,
            'sensor_jumps': self._capture.sensor_jumps,
        }

    @property
    def sensor_scatter(self):
        """Return the sensor bands that the scatter at still links would take (Capture)."""
        return self._capture.sensor_scatter()

    @property
    def last_unpaired(self):
        """Return why the latest pose that could not be paired was not, or ''."""
        return self._pairer.last_unpaired

    @property
    def held(self):
        """
        Return the streams (as Rejected.what names them) whose last pose is held undecided.

        A pose far behind its stream waits for the next message to say whether it was a stale
        one or a time jump (module docstring): it is neither good nor bad until then.
        """
        if not self._behind:   # (nearly always: asked after every pose)
            return _NONE_HELD
        return frozenset(TOPICS[stream] for stream in self._behind)

    def end_streams(self):
        """
        Say that no message follows (a recording ended); return the events of that.

        A pose still held undecided (`held`) is rejected as stale: no message confirmed a jump.
        """
        events = [self._stale(stream, error, 'the recording ended after it')
                  for stream, (_, _, error) in self._behind.items()]
        self._behind.clear()
        return events

    @property
    def paired_seconds(self):
        """Return the seconds of stamps the paired poses cover (capture.Capture.paired_ns)."""
        return self._capture.paired_ns / NS_PER_S

    @property
    def rates_hz(self):
        """Observed rate of each stream, {'link': Hz or None, 'sensor': Hz or None}."""
        return self._pairer.rates_hz()

    # --- internals -----------------------------------------------------------------------

    def _sample_count(self):
        return len(self._calibrator.samples)

    def _add_pose(self, stream, stamp_ns, pose):
        events = self.pop_events() if self._pending else []
        self._counts[stream] += 1
        if not _finite(pose):
            return events + [self._reject(TOPICS[stream], 'non-finite numbers in the pose',
                                          'non_finite')]
        try:
            pairs = self._pairer.add(stream, stamp_ns, pose)
        except OutOfOrderStamp as error:
            if error.jump_ns <= self.config.time_jump_ns:
                return events + [self._reject(TOPICS[stream], *_late_reason(error))]
            if not self._behind:   # held until the next message says which it was
                self._behind[stream] = (stamp_ns, pose, error)
                return events
            return events + self._new_timeline(stream, stamp_ns, pose)
        if stream in self._behind:   # its stream went on: it was a stale message
            events.append(self._stale(stream, self._behind.pop(stream)[2]))
        return events + self._paired(pairs)

    def _paired(self, pairs):
        """Return the events of the Pairs that one pose completed (notices, samples)."""
        if not pairs and self._pairer.unpaired_total == self._unpaired_seen:
            return []   # most poses: nothing happened
        events = self._unpaired_notice(bool(pairs))
        if pairs and not self._counts['pairing_notices']:
            events += self._pairing_notice()
        for pair in pairs:
            self._counts['pairs'] += 1
            sample = self._capture.add_pair(pair)
            if sample is not None:
                events += self._store_captured(sample)
        return events

    def _copy_of(self, sample):
        """Return the index of the stored sample whose poses `sample` repeats, or None."""
        return self._copies.index_of(sample)

    def _repeated(self, position, copied):
        """Count a ready sample (the `position`-th given) that repeats sample `copied`."""
        self._counts['repeated_samples'] += 1
        return Rejected('sample', f'sample {position} of those given repeats sample {copied} '
                        f'(the same link and sensor poses to within {REPEAT_TOLERANCE:g} m and '
                        f"{REPEAT_TOLERANCE:g} in each quaternion component, a quaternion's "
                        'sign aside: a copied row, not a new measurement): not added twice',
                        'repeated', position, copied)

    def _store_captured(self, sample):
        """Store a sample taken from the streams, unless it repeats an earlier one."""
        repeated = self._repeat_of(sample)
        if repeated is None:
            return self._store(sample)
        return [Notice(self._replayed(f'sample at stamp {sample.stamp_ns * 1e-9:.3f} s',
                                      repeated))]

    def _replayed(self, what, repeated):
        """Count a still from the streams that repeats sample `repeated`; say so of `what`."""
        self._counts['repeated_samples'] += 1
        return f'{what} repeats sample {repeated} (the same data played again): not added twice'

    def _repeat_of(self, sample):
        """
        Return the index of the earlier sample that `sample` repeats, or None.

        The same poses (module docstring); or, only after a time jump, stamps within
        the still window and link poses within the still bands (a new sample needs a motion of
        twice the bands, so within one timeline no two samples are this close).
        """
        copied = self._copy_of(sample)
        if copied is not None or not self._counts['time_jumps']:
            return copied
        capture = self.config.capture
        for index, old in enumerate(self.samples):
            if abs(old.stamp_ns - sample.stamp_ns) <= capture.window_ns:
                angle, distance = pose_change(sample.link, old.link)
                if (angle <= capture.rotation_band_deg
                        and distance <= capture.translation_band_m):
                    return index
        return None

    def _store(self, sample):
        self._copies.add(sample)
        self._calibrator.add_sample(sample)
        self._capture.note_sample(sample)
        if self._on_sample is not None:
            self._on_sample(sample)
        return [SampleCaptured(self._sample_count() - 1, sample)]

    def _reject(self, what, reason, code=''):
        self._counts['rejected'] += 1
        return Rejected(what, reason, code)

    def _pairing_notice(self):
        """Return [the Notice of which stream is interpolated and the rates], once known."""
        rates = self._pairer.typical_rates_hz()
        if rates is None:
            return []
        self._counts['pairing_notices'] += 1
        faster = self._pairer.faster
        slower = LINK if faster == SENSOR else SENSOR
        return [Notice(f'pairing by header stamps: {faster} poses ({rates[faster]:.3g} Hz) '
                       f'interpolated at the {slower} stamps ({rates[slower]:.3g} Hz)')]

    def _new_timeline(self, stream, stamp_ns, pose):
        """
        Start the timeline the held message and this one agree on; return the events.

        A held message of the other stream that is not near this one (more than time_jump_ns
        away) is no part of it: a stale message whose stream paused after it, rejected.
        """
        held = list(self._behind.items())
        self._behind.clear()
        self._pairer.reset()
        self._capture.clear_window()
        self._counts['time_jumps'] += 1
        jump_ns = held[0][1][2].jump_ns
        events = [Notice(f'time jumped back by {jump_ns * 1e-9:.1f} s (bag replayed?): '
                         'pairing buffers cleared, samples kept', code='time_jump')]
        for name, (held_ns, held_pose, error) in held + [(stream, (stamp_ns, pose, None))]:
            if name != stream and abs(held_ns - stamp_ns) > self.config.time_jump_ns:
                events.append(self._stale(name, error))
                continue
            try:
                events += self._paired(self._pairer.add(name, held_ns, held_pose))
            except OutOfOrderStamp as late:   # behind the held message of its stream
                events.append(self._reject(TOPICS[name], *_late_reason(late)))
        return events

    def _stale(self, stream, error,
               why='the next one went on from where the stream was'):
        """Reject a held message far behind its stream that no jump followed."""
        return self._reject(
            TOPICS[stream], f'stamp {error.jump_ns * 1e-9:.3g} s older than the previous '
            f'message, and {why}: a stale message, not a time jump: dropped', 'stale_stamp')

    def _unpaired_notice(self, paired):
        """Return a Notice when UNPAIRED_NOTICE_AFTER poses in a row could not be paired."""
        total = self._pairer.unpaired_total
        before = 0 if paired else self._unpaired_streak
        self._unpaired_streak = before + total - self._unpaired_seen
        self._unpaired_seen = total
        if before < UNPAIRED_NOTICE_AFTER <= self._unpaired_streak:
            return [Notice(f'{self._unpaired_streak} poses in a row could not be paired: '
                           f'{self._pairer.last_unpaired}')]
        return []
