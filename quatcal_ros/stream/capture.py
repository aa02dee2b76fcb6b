"""
Samples from the paired pose stream: still captures (auto, manual) or rotation steps.

Modes:
- 'auto': when the link and sensor poses have both stayed within their bands for a window of
  stamps, take one sample, the average of the window (quaternion.average for rotations, the
  mean for positions), which beats the noise of a single frame.  The next sample comes only
  after a real motion (the link has departed more than min_departure_deg or min_departure_m from
  the last sample) and a new still window.
- 'manual': a sample only on request (`capture_now`), from the latest still window; refused,
  with the reason, while the robot moves, when no recent pair exists, or before a motion.
- 'continuous': for recordings without stops, the single pair at which the link has rotated
  at least continuous_step_deg since the last sample; no averaging.

"Still for a window" means: every pair from the last one at least window_ns older than the
newest up to the newest lies within the bands of the newest pose, so a gap in the stream
cannot hide a motion. The sensor poses may break that at a few frames inside the window (at
most one in MAX_OUTSIDE_SHARE, never the oldest, so the object stood where it stands now a
whole window ago):
- frames just outside a sensor band are the detector's noise, and averaged: the difference
  of two frames with 0.3 deg of noise per axis passes 1 deg at one frame in eight, so a
  manual capture at a real stop was refused 7 times in 10 (at 0.4 deg, always);
- frames that jump beyond JUMP_BANDS times a band (a marker that flips, a detection of the
  wrong thing) are left out of the sample, and counted: before, one cost the whole stop
  without a word (a tenth of the frames flipped lost 12 of 15 stops of a recording).
Quaternions are (w, x, y, z); stamps are integer nanoseconds.
"""

from collections import deque
from dataclasses import dataclass
import math

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose, Sample
from quatcal_ros.stream.pose_buffer import PoseBuffer

MODES = ('auto', 'manual', 'continuous')
# Consecutive pairs further apart than this (header stamps) do not count as paired time:
# Capture.paired_ns, the /diagnostics rule for a robot that never stops. A detector at 0.2 Hz
# still counts; the streams paused longer (the marker out of view) do not.
PAIRED_STEP_NS = 5_000_000_000
# At most one sensor pose in this many of a still window may be outside the sensor bands of the
# newest (module doc): a quarter keeps a majority of three in four around it.
MAX_OUTSIDE_SHARE = 4
# The start of a still window's refusal for the sensor's poses (Capture.unsteady_sensor counts).
SENSOR_NOT_STEADY = 'sensor pose is not steady'
# A sensor pose this many sensor bands from the newest is a jump, not noise (a marker flip
# turns the pose by tens of degrees; a detector's noise that reaches twice the band needs
# wider bands).
JUMP_BANDS = 2.0
# The sensor's scatter while the link stood still, for the bands to suggest (sensor_scatter):
# each refused window's 75th percentile of the sensor poses' changes from the newest (a window
# may have a quarter outside: MAX_OUTSIDE_SHARE), the median over the latest SCATTER_WINDOWS
# windows, times SCATTER_MARGIN. On a detector scattering 2 deg per axis that is 1.3-1.7 times
# the narrowest band that takes a sample in a 1.2 s stop (test_message_checks.py).
SCATTER_WINDOWS = 200
SCATTER_MARGIN = 1.2


@dataclass(frozen=True)
class CaptureConfig:
    """
    How samples are taken; angles in degrees, lengths in metres, durations in ns (stamps).

    rotation_band_deg, translation_band_m: how much the link may move and still be still.
    sensor_rotation_band_deg, sensor_translation_band_m: the same for the sensor pose, whose
        detection noise is larger.
    min_departure_deg, min_departure_m: how far the link must move away from the last sample before
        the next still capture (either suffices).
    min_still_pairs: fewest pairs a still window must hold.
    recent_ns: a manual capture needs a pair at most this old.
    continuous_step_deg: link rotation between two samples in 'continuous' mode.
    """

    mode: str = 'auto'
    window_ns: int = 500_000_000
    rotation_band_deg: float = 0.2
    translation_band_m: float = 0.001
    sensor_rotation_band_deg: float = 1.0
    sensor_translation_band_m: float = 0.005
    min_departure_deg: float = 2.0
    min_departure_m: float = 0.02
    min_still_pairs: int = 3
    recent_ns: int = 1_000_000_000
    continuous_step_deg: float = 5.0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f'capture mode must be one of {MODES}, not {self.mode!r}')
        numbers = [getattr(self, name) for name in self.__dataclass_fields__ if name != 'mode']
        if not all(np.isfinite(numbers)) or min(numbers) <= 0:
            raise ValueError(f'capture settings must be positive and finite: {self}')
        if self.min_departure_deg <= self.rotation_band_deg:
            raise ValueError(f'min_departure_deg ({self.min_departure_deg}) must exceed '
                             f'rotation_band_deg ({self.rotation_band_deg})')
        if self.min_departure_m <= self.translation_band_m:
            raise ValueError(f'min_departure_m ({self.min_departure_m}) must exceed '
                             f'translation_band_m ({self.translation_band_m})')


def _short(number):
    """Format a number for a message: at most two decimals, no exponent."""
    return f'{round(float(number), 2):g}'


def pose_change(pose, reference):
    """Rotation (deg) and translation (m) between two poses."""
    angle = math.degrees(quat.angle_between(pose.quaternion, reference.quaternion))
    dx, dy, dz = (pose.position - reference.position).tolist()
    return angle, math.sqrt(dx * dx + dy * dy + dz * dz)


class _PairWindow:
    """
    The latest pairs, trimmed to the still-window check (module doc), and their statistics.

    The link and the sensor poses are two PoseBuffers with the same stamps.
    """

    def __init__(self, window_ns):
        self.window_ns = window_ns
        self.link = PoseBuffer()
        self.sensor = PoseBuffer()

    def __len__(self):
        return len(self.link)

    def clear(self):
        self.link.clear()
        self.sensor.clear()

    def append(self, pair):
        self.link.append(pair.stamp_ns, pair.link)
        self.sensor.append(pair.stamp_ns, pair.sensor)
        self._trim()

    def _trim(self):
        """Keep the last pair >= window_ns old (if not > 2 window_ns old) and all newer."""
        newest = self.link.newest_ns
        keep_from = newest - 2 * self.window_ns
        boundary = self.link.last_at_or_before(newest - self.window_ns)
        if boundary is not None:
            keep_from = max(keep_from, boundary)
        self.link.forget_older_than(keep_from)
        self.sensor.forget_older_than(keep_from)

    @property
    def span_ns(self):
        return self.link.span_ns

    def _arrays(self):
        """Return the kept quaternions (2, n, 4) and positions (2, n, 3): [0] link, [1] sensor."""
        poses = self.link.poses() + self.sensor.poses()
        return (np.concatenate([pose.quaternion for pose in poses]).reshape(2, -1, 4),
                np.concatenate([pose.position for pose in poses]).reshape(2, -1, 3))

    def oldest_change(self):
        """Return the change (deg, m) of the oldest pair from the newest: link, then sensor."""
        link, sensor = self.link.poses_at_ends(), self.sensor.poses_at_ends()
        return pose_change(*link) + pose_change(*sensor)

    def changes(self):
        """Rotation (deg) and translation (m) of every kept pose from the newest: (2, n) each."""
        q, p = self._arrays()
        return (np.degrees(quat.angle_between(q, q[:, -1:])),
                np.linalg.norm(p - p[:, -1:], axis=-1))

    def average_sample(self, left_out=None):
        """
        One Sample: the mean of the kept pairs, stamped at the middle of their span.

        When most sensor poses of the window have a covariance, the sample's is the mean of
        theirs (one frame without, an all-zero covariance or a frame the detector sent bare,
        had left the sample without one, and the session's every sample with it:
        calibration.sensor_covariance_factors): not divided by the number of frames, whose
        errors in a still window are mostly shared (the same view of the target); refine fits
        the overall scale anyway. left_out: a mask of the sensor poses not averaged (jumps).
        """
        q, p = self._arrays()
        kept = np.ones(len(self), bool) if left_out is None else ~left_out
        stamp = self.link.oldest_ns + self.span_ns // 2
        poses = [pose for pose, keep in zip(self.sensor.poses(), kept) if keep]
        given = [pose.covariance for pose in poses if pose.covariance is not None]
        # (each divided first: the sum of covariances of 1e308 that each message may give
        # overflowed to inf)
        covariance = (np.sum(np.asarray(given) / len(given), axis=0)
                      if 2 * len(given) > len(poses) else None)
        return Sample(stamp, Pose(p[0].mean(axis=0), quat.average(q[0])),
                      Pose(p[1][kept].mean(axis=0), quat.average(q[1][kept]), covariance))


def _round_up(value):
    """Return `value` > 0 rounded up to two significant digits."""
    step = 10.0 ** (math.floor(math.log10(value)) - 1)
    return round(math.ceil(value / step - 1e-9) * step, 12)


def unsteady_sensor_note(count, config, band_names, scatter=None):
    """
    Say that at `count` paired poses the link stood still but the sensor pose did not, or ''.

    config: the CaptureConfig; band_names: what the reader sets the two sensor bands with
    (the node's parameters, the tools' options); scatter: Capture.sensor_scatter(), the
    bands to suggest.
    """
    if not count:
        return ''
    widen = ', '.join(band_names)
    if scatter is not None:
        widen = ', '.join(f'{name} {value:g}' for name, value in zip(band_names, scatter))
        widen += ': what the scatter seen there takes'
    return (f'; at {count} paired poses the link stood still but the sensor pose moved beyond '
            f'its bands ({config.sensor_rotation_band_deg:g} deg, '
            f'{config.sensor_translation_band_m:g} m): for a sensor that noisy widen them '
            f'({widen})')


class Capture:
    """Takes samples from the paired stream in one of the MODES (module docstring)."""

    def __init__(self, config=CaptureConfig()):
        self.config = config
        self._window = _PairWindow(config.window_ns)
        self._newest = None
        self._last_sample = None
        self._moved = True
        # Pairs at which the link stayed within its still bands but the sensor pose did not:
        # what keeps a noisy sensor from ever giving a still sample (its bands are too tight).
        self.unsteady_sensor = 0
        self._scatter = deque(maxlen=SCATTER_WINDOWS)   # (deg, m) of those windows
        # Sensor poses left out of the still samples taken: they jumped over JUMP_BANDS times
        # the sensor bands for a frame or a few (module doc).
        self.sensor_jumps = 0
        # The stamps this timeline's pairs cover: the steps between consecutive pairs up to
        # PAIRED_STEP_NS (a pause of the streams, or stamps that leap, is not paired time).
        self.paired_ns = 0

    def reconfigure(self, config):
        """
        Capture with `config` from now on (a runtime change).

        The last sample stays; the still window starts anew, and so do the counts judged by
        the old bands and window (the advice to widen the bands, the time without a still
        sample).
        """
        self.config = config
        self._window = _PairWindow(config.window_ns)
        self._newest = None
        self.unsteady_sensor, self.paired_ns = 0, 0
        self._scatter.clear()

    def clear_window(self):
        """Forget the recent pairs only (time jumped); the next capture still needs a motion."""
        self._window.clear()
        self._newest = None
        self.paired_ns = 0

    def note_sample(self, sample):
        """Record a sample taken elsewhere (CSV, resume): the next one needs a motion from it."""
        self._last_sample = sample
        self._moved = False

    def add_pair(self, pair):
        """Add the next Pair (stamps increasing); return the Sample it completes, or None."""
        if self._newest is not None and pair.stamp_ns - self._newest.stamp_ns <= PAIRED_STEP_NS:
            self.paired_ns += pair.stamp_ns - self._newest.stamp_ns
        self._window.append(pair)
        self._newest = pair
        if not self._moved:   # (also in continuous mode: a manual capture asks)
            angle, distance = pose_change(pair.link, self._last_sample.link)
            self._moved = (angle > self.config.min_departure_deg
                           or distance > self.config.min_departure_m)
        if self.config.mode == 'continuous':
            return self._continuous_sample(pair)
        if self.config.mode == 'auto' and self._moved and self._is_still():
            return self._take_window()[0]
        return None

    def capture_now(self, now_ns):
        """Sample from the latest still window: (Sample, description) or (None, refusal)."""
        if self._newest is None or self._newest.stamp_ns < now_ns - self.config.recent_ns:
            return None, (f'no paired poses in the last {self.config.recent_ns * 1e-9:.1f} s: '
                          'check that both topics publish and that their stamps use the same '
                          'clock')
        refusal = self._still_reason() or self._motion_reason()
        if refusal:
            return None, refusal
        sample, jumps = self._take_window()
        pairs = len(self._window)
        if not jumps:
            return sample, f'averaged {pairs} pairs over {self._window.span_ns * 1e-9:.2g} s'
        return sample, (f'averaged {pairs} link and {pairs - jumps} sensor poses over '
                        f'{self._window.span_ns * 1e-9:.2g} s, {jumps} sensor pose(s) left '
                        f'out: they jumped over {JUMP_BANDS:g}x the sensor bands (a marker '
                        'flip?)')

    def _take_window(self):
        """Take the still window's sample (_still_reason has just passed it), and its jumps."""
        jumps = self._jumped(*self._window.changes())
        self.sensor_jumps += int(jumps.sum())
        return self._take(self._window.average_sample(jumps)), int(jumps.sum())

    def _jumped(self, degrees, metres):
        """Return the mask of the sensor poses beyond JUMP_BANDS sensor bands (changes())."""
        config = self.config
        return ((degrees[1] > JUMP_BANDS * config.sensor_rotation_band_deg)
                | (metres[1] > JUMP_BANDS * config.sensor_translation_band_m))

    def _take(self, sample):
        self.note_sample(sample)
        return sample

    def _continuous_sample(self, pair):
        if self._last_sample is not None:
            angle, _ = pose_change(pair.link, self._last_sample.link)
            if angle < self.config.continuous_step_deg:
                return None
        return self._take(Sample(pair.stamp_ns, pair.link, pair.sensor))

    def _is_still(self):
        """Return whether _still_reason() is None; while the robot moves, from one pair."""
        # The oldest pair outside a band decides it without the others (the spread is the
        # largest change from the newest): most pairs of a motion.
        config = self.config
        link_deg, link_m, sensor_deg, sensor_m = self._window.oldest_change()
        if link_deg > config.rotation_band_deg or link_m > config.translation_band_m:
            return False
        if (sensor_deg > config.sensor_rotation_band_deg
                or sensor_m > config.sensor_translation_band_m):
            self._note_unsteady()
            return False
        reason = self._still_reason()
        if reason and reason.startswith(SENSOR_NOT_STEADY):
            self._note_unsteady()
        return reason is None

    def _note_unsteady(self):
        """Count a window where the link stood still but the sensor did not; keep its scatter."""
        self.unsteady_sensor += 1
        degrees, metres = self._window.changes()
        self._scatter.append((np.percentile(degrees[1], 75), np.percentile(metres[1], 75)))

    def sensor_scatter(self):
        """
        Return the sensor bands that would take most still windows refused so far, or None.

        (deg, m): SCATTER_MARGIN times the median of the refused windows' 75th percentile of
        the sensor's changes from the newest pose, each at least the band it is now, rounded
        up to two significant digits.
        """
        if not self._scatter:
            return None
        wanted = SCATTER_MARGIN * np.median(np.array(self._scatter), axis=0)
        config = self.config
        return tuple(_round_up(max(value, band)) for value, band in zip(
            wanted, (config.sensor_rotation_band_deg, config.sensor_translation_band_m)))

    def _still_reason(self):
        """Why the latest window is not still, or None when it is."""
        config = self.config
        window = self._window
        span_s = window.span_ns * 1e-9
        if window.span_ns < config.window_ns:
            return (f'paired poses cover only {span_s:.2g} s of the {config.window_ns * 1e-9:.2g}'
                    ' s still window: wait and try again')
        if len(window) < config.min_still_pairs:
            return (f'only {len(window)} paired poses in the last {span_s:.2g} s (need '
                    f'{config.min_still_pairs}): is the sensor dropping frames?')
        degrees, metres = window.changes()
        (link_deg, sensor_deg), (link_m, sensor_m) = degrees.max(axis=1), metres.max(axis=1)
        if link_deg > config.rotation_band_deg:
            return (f'robot is moving: link rotated {_short(link_deg)} deg in the last '
                    f'{span_s:.2g} s (band {_short(config.rotation_band_deg)} deg)')
        if link_m > config.translation_band_m:
            return (f'robot is moving: link moved {_short(link_m * 1e3)} mm in the last '
                    f'{span_s:.2g} s (band {_short(config.translation_band_m * 1e3)} mm)')
        band_deg, band_m = config.sensor_rotation_band_deg, config.sensor_translation_band_m
        jumps = self._jumped(degrees, metres)

        def too_many(outside):   # the oldest frame, or over one in MAX_OUTSIDE_SHARE
            return outside[0] or MAX_OUTSIDE_SHARE * outside.sum() > len(window)
        rotation, translation = degrees[1] > band_deg, metres[1] > band_m
        if too_many(rotation | translation) or len(window) - jumps.sum() < config.min_still_pairs:
            beyond = [name for name, outside in (('rotation', rotation),
                                                 ('translation', translation))
                      if too_many(outside)]
            which = (f'the {" and the ".join(beyond)} beyond' if beyond else
                     f'{len(window) - jumps.sum()} frames within them, {jumps.sum()} jumped: '
                     f'min_still_pairs is {config.min_still_pairs}')
            return (f'{SENSOR_NOT_STEADY}: {_short(sensor_deg)} deg, '
                    f'{_short(sensor_m * 1e3)} mm in the last {span_s:.2g} s (bands '
                    f'{_short(band_deg)} deg, {_short(band_m * 1e3)} mm; {which}): is the '
                    'object fixed and detected reliably? Just after a stop the sensor (its '
                    'latency) may still show the motion: try again in a moment. A detector '
                    'this noisy at a real stop needs wider sensor bands')
        return None

    def _motion_reason(self):
        """Why the link has not moved enough since the last sample, or None when it has."""
        if self._moved:
            return None
        angle, distance = pose_change(self._newest.link, self._last_sample.link)
        config = self.config
        return (f'no motion since the last sample (link {_short(angle)} deg, '
                f'{_short(distance * 1e3)} mm away; need '
                f'{_short(config.min_departure_deg)} deg or '
                f'{_short(config.min_departure_m * 1e3)} mm): move the robot first')
