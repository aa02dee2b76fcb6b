"""
Pair the link-pose and sensor-pose streams by header stamp.

The link stream (T_base_link, typically 50-1000 Hz) and the sensor stream (T_sensor_obj, a
camera at 10-60 Hz, late and with dropped frames) are not synchronised.  The faster stream,
chosen from the observed rates, is interpolated at each stamp of the slower one: position
linearly, rotation by SLERP (exact for a constant angular velocity), and only between two
neighbouring samples that bracket the stamp and are at most `max_gap_ns` apart.  Without such
a bracket, a sample within `tolerance_ns` of the stamp is used as it is; otherwise the stamp
stays unpaired (nothing is paired across a gap).

A slower-stream stamp is resolved once the faster stream has reached it, so a camera frame
that arrives 30 ms late pairs as soon as it arrives and a link pose that arrives late pairs
when it comes.  Stamps are integer nanoseconds; quaternions are (w, x, y, z).  Each stream
must have strictly increasing stamps: an older or repeated stamp raises `OutOfOrderStamp`
and leaves the pairer unchanged; the caller decides between dropping it and `reset()`.

Each stream's recent poses are a pose_buffer.PoseBuffer (whose `at` is the rule above).
Cost per message: an append, an O(log n) bisection and amortised O(1) trimming.
`add_many` takes a run of the faster stream at once (an offline replay), with the result of
adding its poses one by one.
"""

from collections import Counter
from dataclasses import dataclass
from typing import NamedTuple

from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.pose_buffer import OLDER, PoseBuffer, StampNotNewer

LINK = 'link'
SENSOR = 'sensor'

# A stream's rate (rates_hz) is the median interval of its newest RATE_INTERVALS stamps (the
# slower stream asks at every pose), once it keeps MIN_RATE_POSES. Which stream is faster is
# decided once both keep RATE_POSES, or MIN_RATE_POSES spanning half the window (a detector
# so slow that its window never keeps more): the median of three intervals survives one lost
# or late message among the first of a subscription, the two of three stamps do not. From
# then on the slower stream takes over as the interpolated one only when clearly faster
# (ROLE_SWITCH_RATIO, hysteresis). The rates are said (typical_rates_hz) once RATE_POSES span
# RATE_SPAN_NS (or half the window when that is shorter); a stream too slow to keep
# RATE_POSES in the window has none said.
MIN_RATE_POSES = 3
RATE_POSES = 4
RATE_INTERVALS = 16
ROLE_SWITCH_RATIO = 1.5
RATE_SPAN_NS = 500_000_000


@dataclass(frozen=True)
class PairingConfig:
    """
    Pairing limits; durations are integer nanoseconds on header stamps.

    tolerance_ns: without an interpolation bracket, a sample this close to the stamp is
        paired as it is.
    max_gap_ns: the two samples an interpolation uses may be at most this far apart.
    window_ns: each stream keeps the samples of this last stretch of its own stamps; it must
        exceed the sensor's latency.
    max_length: each stream keeps at most this many samples.
    """

    tolerance_ns: int = 1_000_000
    max_gap_ns: int = 100_000_000
    window_ns: int = 2_000_000_000
    max_length: int = 5000

    def __post_init__(self):
        if self.tolerance_ns < 0 or min(self.max_gap_ns, self.window_ns, self.max_length) <= 0:
            raise ValueError(f'pairing limits must be positive: {self}')
        if self.window_ns <= self.max_gap_ns:
            raise ValueError(f'pairing window_ns ({self.window_ns}) must exceed max_gap_ns '
                             f'({self.max_gap_ns})')


class Pair(NamedTuple):
    """Both poses at one header stamp: link is T_base_link, sensor is T_sensor_obj."""

    stamp_ns: int
    link: Pose
    sensor: Pose


class OutOfOrderStamp(ValueError):
    """A stamp not newer than the previous one of its stream; the message was not used."""

    def __init__(self, stream, stamp_ns, previous_ns):
        self.stream = stream
        self.stamp_ns = stamp_ns
        self.previous_ns = previous_ns
        self.jump_ns = previous_ns - stamp_ns
        super().__init__(f'{stream} stamp {stamp_ns} ns is {self.jump_ns * 1e-9:.6g} s older '
                         f'than the previous {stream} stamp ({previous_ns} ns)')


class Pairer:
    """Turns the two pose streams into Pairs at the slower stream's stamps (module docstring)."""

    def __init__(self, config=PairingConfig()):
        self.config = config
        self._streams = {name: PoseBuffer(config.window_ns, config.max_length)
                         for name in (LINK, SENSOR)}
        self._faster = None
        self._resolved_until_ns = None
        self.unpaired = Counter()   # unpaired slower-stream stamps by reason
        self.unpaired_total = 0     # their sum
        self.last_unpaired = ''     # why the latest one was not paired

    @property
    def faster(self):
        """'link' or 'sensor': the stream interpolated at the other's stamps; None until known."""
        return self._faster

    def rates_hz(self):
        """Observed rate of each stream, {'link': Hz or None, 'sensor': Hz or None}."""
        return {name: _rate_hz(stream) for name, stream in self._streams.items()}

    def typical_rates_hz(self):
        """
        Each stream's rate to report, {'link': Hz, 'sensor': Hz}, or None until both are known.

        From the median interval of its newest stamps (a dropped or late message does not
        change it: rates_hz), once it keeps RATE_POSES spanning RATE_SPAN_NS (or half the
        window).
        """
        span_ns = min(RATE_SPAN_NS, self.config.window_ns // 2)
        if any(len(stream) < RATE_POSES or stream.span_ns < span_ns
               for stream in self._streams.values()):
            return None
        return self.rates_hz()

    def buffered(self):
        """Poses kept per stream, {'link': count, 'sensor': count}."""
        return {name: len(stream) for name, stream in self._streams.items()}

    def reset(self):
        """Forget both streams (after time went backwards); the counters are kept."""
        for stream in self._streams.values():
            stream.clear()
        self._faster = None
        self._resolved_until_ns = None

    def add(self, stream_name, stamp_ns, pose):
        """Add a pose of stream 'link' or 'sensor'; raises OutOfOrderStamp, see module doc."""
        stamp_ns = int(stamp_ns)
        stream = self._streams[stream_name]
        try:
            stream.append(stamp_ns, pose)
        except StampNotNewer as error:
            raise OutOfOrderStamp(stream_name, stamp_ns, error.newest_ns) from None
        if stream_name != self._faster:   # roles change only when the slower stream speeds up
            self._update_roles()
        return self._settle(stream)

    def add_many(self, stream_name, stamps_ns, positions, quaternions):
        """
        Add the leading poses of a run of one stream at once; return (how many, their Pairs).

        The same as add() for each of them: the run's longest part of strictly increasing
        stamps, newer than the stream's newest, that ends at the first pose reaching a stamp
        the other stream waits at (a Pairs-completing pose comes last).  Only the faster
        stream is taken this way: otherwise, or when the first stamp is not newer, nothing is
        added and (0, []) is returned, and add() takes that pose (and raises, or changes roles).
        stamps_ns: ints; positions (n, 3), quaternions (n, 4) (w, x, y, z): the poses' rows.
        """
        if stream_name != self._faster:
            return 0, []
        stream = self._streams[stream_name]
        count = stream.extend(stamps_ns, positions, quaternions, self._first_pending_ns())
        if not count:
            return 0, []
        # Poses before the last reach no waiting stamp, so add() would pair nothing at them
        # (nor give up on one: the other stream, whose newest stamp decides that, did not move).
        return count, self._settle(stream)

    def _settle(self, stream):
        """Pair what the poses just added to `stream` complete, then trim it; return the Pairs."""
        pairs = self._resolve_pending() if self._faster else []
        stream.trim()
        return pairs

    def _first_pending_ns(self):
        """Return the oldest slower-stream stamp not yet resolved, or None."""
        slow = self._streams[self._slower]
        if self._resolved_until_ns is None:
            return slow.oldest_ns
        return slow.first_after(self._resolved_until_ns)

    @property
    def _slower(self):
        return LINK if self._faster == SENSOR else SENSOR

    def _update_roles(self):
        if self._faster is None:
            half_window_ns = self.config.window_ns // 2
            if not all(len(stream) >= RATE_POSES or (len(stream) >= MIN_RATE_POSES
                                                     and stream.span_ns >= half_window_ns)
                       for stream in self._streams.values()):
                return   # (checked by counts first: no median of a 1 kHz link's stamps at
                #          every pose while the camera is silent)
            rates = self.rates_hz()
            self._faster = SENSOR if rates[SENSOR] > rates[LINK] else LINK
            return
        rates = self.rates_hz()   # (None for a stream the window kept too few of: a pause)
        if None in rates.values():
            return
        if rates[self._slower] > ROLE_SWITCH_RATIO * rates[self._faster]:
            self._faster = self._slower

    def _resolve_pending(self):
        """Pair every slower-stream stamp the faster stream has now reached, in order."""
        fast = self._streams[self._faster]
        slow = self._streams[self._slower]
        slow_newest_ns = slow.newest_ns
        if slow_newest_ns is None or (self._resolved_until_ns is not None
                                      and slow_newest_ns <= self._resolved_until_ns):
            return []   # nothing waits (most faster-stream messages)
        fast_newest_ns = fast.newest_ns
        pairs = []
        for stamp_ns, slow_pose in slow.after(self._resolved_until_ns):
            if stamp_ns <= fast_newest_ns:
                fast_pose = self._fast_pose_at(fast, stamp_ns)
            elif slow_newest_ns - stamp_ns > self.config.window_ns:
                fast_pose = self._unpaired(
                    'waiting', f'the {self._faster} stream stopped at stamp '
                    f'{fast_newest_ns * 1e-9:.3f} s, {(stamp_ns - fast_newest_ns) * 1e-9:.3f} s '
                    f'before this {self._slower} stamp')
            else:
                break
            self._resolved_until_ns = stamp_ns
            if fast_pose is not None:
                pairs.append(self._pair(stamp_ns, slow_pose, fast_pose))
        return pairs

    def _fast_pose_at(self, fast, stamp_ns):
        """Return the faster stream's pose at stamp_ns (<= its newest), or None if unknown."""
        pose, miss = fast.at(stamp_ns, self.config.max_gap_ns, self.config.tolerance_ns)
        if miss is None:
            return pose
        if miss.reason == OLDER:
            return self._unpaired(
                'outside', f'{self._slower} stamp {stamp_ns * 1e-9:.3f} s is '
                f'{(miss.after_ns - stamp_ns) * 1e-9:.3f} s older than the oldest kept '
                f'{self._faster} pose: latency beyond the {self.config.window_ns * 1e-9:.3g} s '
                'buffer, or stamps from different clocks?')
        return self._unpaired(
            'gap', f'the {self._faster} stream has a gap of '
            f'{(miss.after_ns - miss.before_ns) * 1e-9:.3f} s around {self._slower} stamp '
            f'{stamp_ns * 1e-9:.3f} s (max gap {self.config.max_gap_ns * 1e-9:.3g} s)')

    def _unpaired(self, reason, text):
        self.unpaired[reason] += 1
        self.unpaired_total += 1
        self.last_unpaired = text
        return None

    def _pair(self, stamp_ns, slow_pose, fast_pose):
        if self._faster == LINK:
            return Pair(stamp_ns, fast_pose, slow_pose)
        return Pair(stamp_ns, slow_pose, fast_pose)


def _rate_hz(stream):
    """Rate of a stream's kept poses (a PoseBuffer) by their median interval, or None."""
    if len(stream) < MIN_RATE_POSES:
        return None
    return 1e9 / stream.median_interval_ns(RATE_INTERVALS)
