"""
A time-indexed buffer of poses: (stamp_ns, Pose) kept in increasing stamp order.

The one store behind the package's pose streams: the pairer's two streams, the dynamic edges
of the transform tree and the still window of capture.  Stamps are integer nanoseconds;
quaternions are (w, x, y, z).

- Adding: `append` a pose newer than the newest (else StampNotNewer, nothing changes);
  `extend` with the leading increasing part of a run of rows of arrays (an offline replay:
  a row becomes a Pose only when it is looked at); `insert` at any stamp (late transforms),
  in order and replacing the pose at an equal stamp.
- Looking up (`at`): the pose at an equal stamp, else the one interpolated between the two
  kept poses that bracket the stamp (`interpolate_pose`: position linearly, rotation by SLERP)
  when they are at most `max_gap_ns` apart, else the nearer of the two when within
  `tolerance_ns` of the stamp.  Never extrapolated, never across a longer gap: a Miss says why.
- Forgetting: `trim` keeps the last `window_ns` of stamps before the newest and at most
  `max_length` poses; `forget_older_than` serves a rule of the caller's own.

Plain lists with a moving head index (a deque would make bisection O(n)): lookups are an
O(log n) bisection, appending and forgetting amortised O(1), inserting before the newest O(n).
"""

import bisect
from itertools import islice, repeat
import statistics
from typing import NamedTuple, Optional

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose

# Why a lookup found no pose: the stamp is newer than the newest pose (it may still come),
# older than the oldest kept one, or inside a gap longer than max_gap_ns.
LATER, OLDER, GAP = 'later', 'older', 'gap'
# Forgotten list heads are deleted once they are this long and at least half of the list.
COMPACT_AFTER = 256


def interpolate_pose(pose0, pose1, fraction):
    """
    Pose a `fraction` of the way from pose0 (0.0) to pose1 (1.0): linear, and SLERP.

    Covariances (when both poses have one) are blended linearly too.
    """
    position = pose0.position + fraction * (pose1.position - pose0.position)
    rotation = quat.slerp(pose0.quaternion, pose1.quaternion, fraction)   # unit length
    covariance = None
    if pose0.covariance is not None and pose1.covariance is not None:
        covariance = pose0.covariance + fraction * (pose1.covariance - pose0.covariance)
    return Pose(position, rotation, covariance)


class StampNotNewer(ValueError):
    """A stamp appended that is not newer than the buffer's newest; nothing was added."""

    def __init__(self, stamp_ns, newest_ns):
        self.stamp_ns = stamp_ns
        self.newest_ns = newest_ns
        super().__init__(f'stamp {stamp_ns} ns is not newer than the newest, {newest_ns} ns')


class Miss(NamedTuple):
    """Why `PoseBuffer.at` found no pose: LATER, OLDER or GAP, and the kept stamps around."""

    reason: str
    before_ns: Optional[int]   # the newest kept stamp before the requested one, if any
    after_ns: Optional[int]    # the oldest kept stamp after it, if any


class PoseBuffer:
    """(stamp_ns, Pose) in increasing stamp order, bounded by age and length (module doc)."""

    def __init__(self, window_ns=None, max_length=None):
        """Set the limits of `trim` (None: no limit); nothing is trimmed until it is called."""
        if (window_ns is not None and window_ns <= 0) or \
                (max_length is not None and max_length < 1):
            raise ValueError(f'need window_ns > 0 and max_length >= 1 (or None), not '
                             f'{window_ns} and {max_length}')
        self.window_ns = window_ns
        self.max_length = max_length
        self.clear()

    def clear(self):
        """Forget every pose."""
        # The kept poses are those from index _start on; they are none only when the lists
        # are empty.  An entry of _poses is a Pose or a row (positions, quaternions, index).
        self._stamps = []
        self._poses = []
        self._start = 0

    def __len__(self):
        return len(self._stamps) - self._start

    @property
    def newest_ns(self):
        """Return the newest stamp, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    @property
    def oldest_ns(self):
        """Return the oldest kept stamp, or None when empty."""
        return self._stamps[self._start] if self._stamps else None

    @property
    def span_ns(self):
        """Return the time from the oldest kept stamp to the newest (0 when empty)."""
        return self._stamps[-1] - self._stamps[self._start] if self._stamps else 0

    def median_interval_ns(self, recent=None):
        """
        Return the median interval between kept stamps (ns), or None with fewer than two.

        recent: of the newest `recent` intervals only (a bounded cost at any rate).
        """
        if len(self) < 2:
            return None
        stamps = self._stamps
        first = self._start if recent is None else max(self._start, len(stamps) - recent - 1)
        return statistics.median(b - a for a, b in zip(islice(stamps, first, None),
                                                       islice(stamps, first + 1, None)))

    # --- adding ------------------------------------------------------------------------

    def append(self, stamp_ns, pose):
        """Add a pose newer than the newest; raises StampNotNewer (and adds nothing) if not."""
        stamps = self._stamps
        if stamps and stamp_ns <= stamps[-1]:
            raise StampNotNewer(stamp_ns, stamps[-1])
        stamps.append(stamp_ns)
        self._poses.append(pose)

    def extend(self, stamps_ns, positions, quaternions, stop_at_ns=None):
        """
        Append the leading poses of a run given as rows; return how many were added.

        The same as append() of each pose in turn up to the first stamp that is not newer
        than the one before it (none added when the first is not newer than the newest), and
        with stop_at_ns, up to and including the first pose at or after that stamp.
        stamps_ns: a list of ints; positions (n, 3), quaternions (n, 4): the poses' rows,
        which the buffer keeps (do not change them) and turns into Poses when looked at.
        """
        stamps = self._stamps
        if not stamps_ns or (stamps and stamps_ns[0] <= stamps[-1]):
            return 0
        count = len(stamps_ns)
        for index in range(1, count):
            if stamps_ns[index] <= stamps_ns[index - 1]:
                count = index
                break
        if stop_at_ns is not None:
            count = min(count, bisect.bisect_left(stamps_ns, stop_at_ns, 0, count) + 1)
        stamps.extend(stamps_ns[:count])
        self._poses.extend(zip(repeat(positions), repeat(quaternions), range(count)))
        return count

    def insert(self, stamp_ns, pose):
        """
        Add a pose at any stamp, in order; return whether it was stored.

        A pose at the stamp of a kept one replaces it.  One older than every kept pose and
        older than window_ns before the newest is not stored (the next trim would forget it).
        """
        stamps = self._stamps
        if not stamps or stamp_ns > stamps[-1]:
            stamps.append(stamp_ns)
            self._poses.append(pose)
            return True
        index = bisect.bisect_left(stamps, stamp_ns, self._start)
        if stamps[index] == stamp_ns:
            self._poses[index] = pose
            return True
        if (index == self._start and self.window_ns is not None
                and stamps[-1] - stamp_ns > self.window_ns):
            return False
        stamps.insert(index, stamp_ns)
        self._poses.insert(index, pose)
        return True

    # --- looking up --------------------------------------------------------------------

    def at(self, stamp_ns, max_gap_ns=None, tolerance_ns=0):
        """
        Return (the pose at stamp_ns, None), or (None, a Miss saying why there is none).

        Exact at a kept stamp; between two kept poses at most max_gap_ns apart (None: any),
        interpolated; otherwise the nearer neighbour within tolerance_ns (the later one on a
        tie).  A stamp newer than the newest is always a Miss (LATER).
        """
        stamps = self._stamps
        if not stamps or stamp_ns > stamps[-1]:
            return None, Miss(LATER, self.newest_ns, None)
        after = bisect.bisect_left(stamps, stamp_ns, self._start)
        after_ns = stamps[after]
        if after_ns == stamp_ns:
            return self._pose(after), None
        before = after - 1
        if before < self._start:
            if after_ns - stamp_ns <= tolerance_ns:
                return self._pose(after), None
            return None, Miss(OLDER, None, after_ns)
        before_ns = stamps[before]
        if max_gap_ns is None or after_ns - before_ns <= max_gap_ns:
            fraction = (stamp_ns - before_ns) / (after_ns - before_ns)
            return interpolate_pose(self._pose(before), self._pose(after), fraction), None
        nearest = before if stamp_ns - before_ns < after_ns - stamp_ns else after
        if abs(stamps[nearest] - stamp_ns) <= tolerance_ns:
            return self._pose(nearest), None
        return None, Miss(GAP, before_ns, after_ns)

    def first_after(self, stamp_ns):
        """Return the oldest kept stamp newer than stamp_ns, or None."""
        index = bisect.bisect_right(self._stamps, stamp_ns, self._start)
        return self._stamps[index] if index < len(self._stamps) else None

    def last_at_or_before(self, stamp_ns):
        """Return the newest kept stamp at or before stamp_ns, or None."""
        index = bisect.bisect_right(self._stamps, stamp_ns, self._start) - 1
        return self._stamps[index] if index >= self._start else None

    def after(self, stamp_ns=None):
        """Yield the kept (stamp_ns, Pose) newer than stamp_ns (all when None), oldest first."""
        first = self._start
        if stamp_ns is not None:
            first = bisect.bisect_right(self._stamps, stamp_ns, first)
        for index in range(first, len(self._stamps)):
            yield self._stamps[index], self._pose(index)

    def poses(self):
        """Return the kept poses, oldest first (a list)."""
        start = self._start
        return [self._pose(index) if type(pose) is tuple else pose
                for index, pose in enumerate(self._poses[start:], start)]

    def poses_at_ends(self):
        """Return the oldest and the newest kept Pose (the same one when only one is kept)."""
        return self._pose(self._start), self._pose(len(self._stamps) - 1)

    def _pose(self, index):
        """Return the Pose at `index` of the lists, built first if it is a row."""
        pose = self._poses[index]
        if type(pose) is tuple:   # a row added by extend(), not looked at before
            positions, quaternions, row = pose
            pose = self._poses[index] = Pose(positions[row], quaternions[row])
        return pose

    # --- forgetting --------------------------------------------------------------------

    def trim(self):
        """Forget the poses older than window_ns before the newest, and all but max_length."""
        stamps = self._stamps
        if not stamps:
            return
        first = self._start
        if self.window_ns is not None and stamps[first] < stamps[-1] - self.window_ns:
            first = bisect.bisect_left(stamps, stamps[-1] - self.window_ns, first)
        if self.max_length is not None:
            first = max(first, len(stamps) - self.max_length)
        if first > self._start:
            self._forget_before(first)

    def forget_older_than(self, stamp_ns):
        """Forget the poses with stamps older than stamp_ns."""
        first = bisect.bisect_left(self._stamps, stamp_ns, self._start)
        if first > self._start:
            self._forget_before(first)

    def _forget_before(self, index):
        if index >= len(self._stamps):
            self.clear()
            return
        self._start = index
        if index >= COMPACT_AFTER and 2 * index >= len(self._stamps):
            del self._stamps[:index]
            del self._poses[:index]
            self._start = 0
