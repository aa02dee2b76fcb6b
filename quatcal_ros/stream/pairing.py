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

Cost per message: an append, an O(log n) bisection and amortised O(1) trimming.
`add_many` takes a run of the faster stream at once (an offline replay), with the result of
adding its poses one by one.
"""

import bisect
from collections import Counter
from dataclasses import dataclass
from itertools import repeat
from typing import NamedTuple

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose

LINK = 'link'
SENSOR = 'sensor'

# Samples each stream needs before its rate, and so which stream is faster, is trusted.
MIN_RATE_SAMPLES = 3
# The slower stream takes over as the interpolated one only when clearly faster (hysteresis).
ROLE_SWITCH_RATIO = 1.5
# Trimmed list heads are deleted once they are this long and at least half of the list.
COMPACT_AFTER = 256


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


def interpolate_pose(pose0, pose1, fraction):
    """Pose a `fraction` of the way from pose0 (0.0) to pose1 (1.0): linear, and SLERP."""
    position = pose0.position + fraction * (pose1.position - pose0.position)
    rotation = quat.normalize(quat.slerp(pose0.quaternion, pose1.quaternion, fraction))
    return Pose(position, rotation)


def _increasing_prefix(stamps_ns):
    """Return the length of the leading strictly increasing part of a list of stamps."""
    for index in range(1, len(stamps_ns)):
        if stamps_ns[index] <= stamps_ns[index - 1]:
            return index
    return len(stamps_ns)


class _StampedPoses:
    """
    One stream's recent poses, oldest first: O(log n) lookup, amortised O(1) trimming.

    Plain lists with a moving head index `start` (a deque would make bisection O(n)).  Poses
    added as rows of arrays (`extend`) stay (positions, quaternions, row) until `pose(index)`
    first needs them: most poses of the faster stream are never looked at.
    """

    def __init__(self):
        self.stamps = []
        self.poses = []
        self.start = 0

    def __len__(self):
        return len(self.stamps) - self.start

    @property
    def last(self):
        return self.stamps[-1]

    def append(self, stamp_ns, pose):
        self.stamps.append(stamp_ns)
        self.poses.append(pose)

    def extend(self, stamps_ns, positions, quaternions):
        """Append the poses of rows of positions (n, 3) and quaternions (n, 4)."""
        self.stamps.extend(stamps_ns)
        self.poses.extend(zip(repeat(positions), repeat(quaternions), range(len(stamps_ns))))

    def pose(self, index):
        """Return the Pose at `index` (of the lists)."""
        pose = self.poses[index]
        if type(pose) is tuple:   # a row added by extend(), not yet needed
            positions, quaternions, row = pose
            pose = self.poses[index] = Pose(positions[row], quaternions[row])
        return pose

    def rate_hz(self):
        """Mean rate over the kept samples, or None with too few of them."""
        count = len(self)
        if count < MIN_RATE_SAMPLES:
            return None
        return (count - 1) * 1e9 / (self.stamps[-1] - self.stamps[self.start])

    def first_after(self, stamp_ns):
        """Index of the first kept sample with a stamp > stamp_ns."""
        return bisect.bisect_right(self.stamps, stamp_ns, self.start)

    def trim(self, window_ns, max_length):
        """Forget samples older than window_ns before the newest, and all but max_length."""
        stamps = self.stamps
        if not stamps or (stamps[self.start] >= stamps[-1] - window_ns
                          and len(stamps) - self.start <= max_length):
            return   # nothing to forget: no bisection
        oldest_kept = bisect.bisect_left(self.stamps, self.stamps[-1] - window_ns, self.start)
        self.start = max(oldest_kept, len(self.stamps) - max_length)
        if self.start >= COMPACT_AFTER and 2 * self.start >= len(self.stamps):
            del self.stamps[:self.start]
            del self.poses[:self.start]
            self.start = 0

    def clear(self):
        self.__init__()


class Pairer:
    """Turns the two pose streams into Pairs at the slower stream's stamps (module docstring)."""

    def __init__(self, config=PairingConfig()):
        self.config = config
        self._streams = {LINK: _StampedPoses(), SENSOR: _StampedPoses()}
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
        return {name: stream.rate_hz() for name, stream in self._streams.items()}

    def buffered(self):
        """Poses kept per stream, {'link': count, 'sensor': count}."""
        return {name: len(stream) for name, stream in self._streams.items()}

    def reset(self):
        """Forget both streams (after time went backwards); the counters are kept."""
        for stream in self._streams.values():
            stream.clear()
        self._faster = None
        self._resolved_until_ns = None

    def add_link(self, stamp_ns, pose):
        """Add a link pose T_base_link; return the Pairs it completes, oldest first."""
        return self.add(LINK, stamp_ns, pose)

    def add_sensor(self, stamp_ns, pose):
        """Add a sensor pose T_sensor_obj; return the Pairs it completes, oldest first."""
        return self.add(SENSOR, stamp_ns, pose)

    def add(self, stream_name, stamp_ns, pose):
        """Add a pose of stream 'link' or 'sensor'; raises OutOfOrderStamp, see module doc."""
        stamp_ns = int(stamp_ns)
        stream = self._streams[stream_name]
        stamps = stream.stamps
        if len(stamps) > stream.start and stamp_ns <= stamps[-1]:
            raise OutOfOrderStamp(stream_name, stamp_ns, stamps[-1])
        stamps.append(stamp_ns)
        stream.poses.append(pose)
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
        stream = self._streams[stream_name]
        if stream_name != self._faster or not stamps_ns or stamps_ns[0] <= stream.last:
            return 0, []
        count = _increasing_prefix(stamps_ns)
        waiting_ns = self._first_pending_ns()
        if waiting_ns is not None:
            count = min(count, bisect.bisect_left(stamps_ns, waiting_ns, 0, count) + 1)
        stream.extend(stamps_ns[:count], positions, quaternions)
        # Poses before the last reach no waiting stamp, so add() would pair nothing at them
        # (nor give up on one: the other stream, whose newest stamp decides that, did not move).
        return count, self._settle(stream)

    def _settle(self, stream):
        """Pair what the poses just added to `stream` complete, then trim it; return the Pairs."""
        pairs = self._resolve_pending() if self._faster else []
        stream.trim(self.config.window_ns, self.config.max_length)
        return pairs

    def _first_pending_ns(self):
        """Return the oldest slower-stream stamp not yet resolved, or None."""
        slow = self._streams[self._slower]
        first = slow.start
        if self._resolved_until_ns is not None:
            first = slow.first_after(self._resolved_until_ns)
        return slow.stamps[first] if first < len(slow.stamps) else None

    @property
    def _slower(self):
        return LINK if self._faster == SENSOR else SENSOR

    def _update_roles(self):
        rates = self.rates_hz()
        if None in rates.values():
            return
        if self._faster is None:
            self._faster = SENSOR if rates[SENSOR] > rates[LINK] else LINK
        elif rates[self._slower] > ROLE_SWITCH_RATIO * rates[self._faster]:
            self._faster = self._slower

    def _resolve_pending(self):
        """Pair every slower-stream stamp the faster stream has now reached, in order."""
        fast = self._streams[self._faster]
        slow = self._streams[self._slower]
        if not slow.stamps or (self._resolved_until_ns is not None
                               and slow.stamps[-1] <= self._resolved_until_ns):
            return []   # nothing waits (most faster-stream messages)
        first = slow.start
        if self._resolved_until_ns is not None:
            first = slow.first_after(self._resolved_until_ns)
        pairs = []
        for index in range(first, len(slow.stamps)):
            stamp_ns = slow.stamps[index]
            if stamp_ns <= fast.last:
                fast_pose = self._fast_pose_at(fast, stamp_ns)
            elif slow.last - stamp_ns > self.config.window_ns:
                fast_pose = self._unpaired(
                    'waiting', f'the {self._faster} stream stopped at stamp {fast.last} ns, '
                    f'{(stamp_ns - fast.last) * 1e-9:.3f} s before this {self._slower} stamp')
            else:
                break
            self._resolved_until_ns = stamp_ns
            if fast_pose is not None:
                pairs.append(self._pair(stamp_ns, slow.pose(index), fast_pose))
        return pairs

    def _fast_pose_at(self, fast, stamp_ns):
        """Return the faster stream's pose at stamp_ns (<= its newest), or None if unknown."""
        after = bisect.bisect_left(fast.stamps, stamp_ns, fast.start)
        after_ns = fast.stamps[after]
        if after_ns == stamp_ns:
            return fast.pose(after)
        before = after - 1
        if before >= fast.start:
            before_ns = fast.stamps[before]
            if after_ns - before_ns <= self.config.max_gap_ns:
                fraction = (stamp_ns - before_ns) / (after_ns - before_ns)
                return interpolate_pose(fast.pose(before), fast.pose(after), fraction)
            nearest = before if stamp_ns - before_ns < after_ns - stamp_ns else after
        else:
            nearest = after
        if abs(fast.stamps[nearest] - stamp_ns) <= self.config.tolerance_ns:
            return fast.pose(nearest)
        if before < fast.start:
            return self._unpaired(
                'outside', f'{self._slower} stamp {stamp_ns} ns is '
                f'{(after_ns - stamp_ns) * 1e-9:.3f} s older than the oldest kept '
                f'{self._faster} pose: latency beyond the {self.config.window_ns * 1e-9:.3g} s '
                'buffer, or stamps from different clocks?')
        return self._unpaired(
            'gap', f'the {self._faster} stream has a gap of {(after_ns - before_ns) * 1e-9:.3f} '
            f's around {self._slower} stamp {stamp_ns} ns (max gap '
            f'{self.config.max_gap_ns * 1e-9:.3g} s)')

    def _unpaired(self, reason, text):
        self.unpaired[reason] += 1
        self.unpaired_total += 1
        self.last_unpaired = text
        return None

    def _pair(self, stamp_ns, slow_pose, fast_pose):
        if self._faster == LINK:
            return Pair(stamp_ns, fast_pose, slow_pose)
        return Pair(stamp_ns, slow_pose, fast_pose)
