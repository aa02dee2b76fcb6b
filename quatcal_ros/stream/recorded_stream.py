"""
A whole recorded pose stream held compactly, for the searches that need all of it at once.

The time-offset search reads both streams of a recording before it can replay them. As a list
of (stamp_ns, Pose) that took about 0.9 KB a pose (two small arrays and their objects): 339 MB
for five minutes of a 1 kHz robot. Here a pose is its stamp and seven floats in growing flat
arrays, 64 bytes; a Pose is built only when one is looked at. A covariance, which few streams
carry, is kept beside its row.
"""

from array import array

import numpy as np
from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.pose_buffer import interpolate_pose


class RecordedStream:
    """(stamp_ns, Pose) in arrival order: append one, extend with rows, iterate, cut runs."""

    def __init__(self):
        self._stamps = array('q')
        self._values = array('d')   # per pose: position (3), quaternion (w, x, y, z)
        self._covariances = {}      # row: 6x6 covariance, for the poses that carry one
        self._lookup = None         # the stamps as an array, for `at`

    @classmethod
    def of(cls, messages):
        """Return the stream of these (stamp_ns, Pose) pairs (a RecordedStream: itself)."""
        if isinstance(messages, cls):
            return messages
        stream = cls()
        for stamp_ns, pose in messages:
            stream.append(stamp_ns, pose)
        return stream

    def __len__(self):
        return len(self._stamps)

    def append(self, stamp_ns, pose):
        """Add one pose at its header stamp (an int)."""
        if pose.covariance is not None:
            self._covariances[len(self._stamps)] = pose.covariance
        self._stamps.append(stamp_ns)
        self._values.frombytes(np.concatenate((pose.position, pose.quaternion)).astype(
            float).tobytes())

    def extend(self, stamps_ns, positions, quaternions_wxyz):
        """Add poses given as rows: stamps (n ints), positions (n, 3), quaternions (n, 4)."""
        self._stamps.extend(stamps_ns)
        rows = np.concatenate((np.asarray(positions, dtype=float).reshape(-1, 3),
                               np.asarray(quaternions_wxyz, dtype=float).reshape(-1, 4)),
                              axis=1)
        self._values.frombytes(np.ascontiguousarray(rows).tobytes())

    def stamps(self):
        """Return every stamp as an int64 array (n,), a copy."""
        return np.array(self._stamps, dtype=np.int64)

    def positions(self):
        """Return every position as an array (n, 3), a copy."""
        return self._rows(slice(0, 3))

    def quaternions(self):
        """Return every quaternion as an array (n, 4), a copy."""
        return self._rows(slice(3, 7))

    def pose(self, index):
        """Return the Pose of row `index`."""
        row = np.frombuffer(self._values, dtype=float, count=7, offset=56 * index).copy()
        return Pose(row[:3], row[3:], self._covariances.get(index))

    def __iter__(self):
        """Yield (stamp_ns, Pose) in arrival order."""
        rows = self._rows()
        covariances = self._covariances
        for index, stamp_ns in enumerate(self._stamps):
            yield stamp_ns, Pose(rows[index, :3], rows[index, 3:], covariances.get(index))

    def runs(self, time_jump_ns):
        """
        Return the stream cut where its stamps jump back by more than time_jump_ns.

        Each run a RecordedStream in stamp order (a late message within a run moved to its
        place; equal stamps keep their arrival order): the timelines of a looped recording or
        a clock restart. A message or two that far from the ones on both sides of them, which
        agree, belong to no timeline (stale or future stamps, which the live checks drop too):
        they are left out (_lone). They had cut a run of one stream only, and the time-offset
        search refused the recording.
        """
        stamps = self.stamps()
        kept = np.flatnonzero(~_lone(stamps, time_jump_ns))
        cuts, latest = [], None
        for position, stamp_ns in enumerate(stamps[kept].tolist()):
            if latest is not None and latest - stamp_ns > time_jump_ns:
                cuts.append(position)
                latest = None
            latest = stamp_ns if latest is None else max(latest, stamp_ns)
        if not cuts and len(kept) == len(stamps) and np.all(stamps[1:] >= stamps[:-1]):
            return [self]
        rows = self._rows()
        runs = []
        for start, stop in zip([0] + cuts, cuts + [len(kept)]):
            order = kept[start + np.argsort(stamps[kept[start:stop]], kind='stable')]
            run = RecordedStream()
            run._stamps.extend(stamps[order].tolist())
            run._values.frombytes(rows[order].tobytes())
            if self._covariances:
                run._covariances = {new: self._covariances[old]
                                    for new, old in enumerate(order.tolist())
                                    if old in self._covariances}
            runs.append(run)
        return runs

    def at(self, stamp_ns):
        """
        Return the pose at stamp_ns of a stream in stamp order (a run), or None outside it.

        Of the poses at one stamp the last stands (as in a PoseBuffer): the pose at an equal
        stamp, else interpolated between the two around it (pose_buffer.interpolate_pose),
        across any gap.
        """
        if self._lookup is None or len(self._lookup) != len(self):
            self._lookup = self.stamps()
        stamps = self._lookup
        index = int(np.searchsorted(stamps, stamp_ns, side='right')) - 1
        if index < 0:
            return None
        if stamps[index] == stamp_ns:
            return self.pose(index)
        if index + 1 == len(stamps):
            return None
        after_ns = int(stamps[index + 1])
        after = int(np.searchsorted(stamps, after_ns, side='right')) - 1   # its last pose
        fraction = (stamp_ns - int(stamps[index])) / (after_ns - int(stamps[index]))
        return interpolate_pose(self.pose(index), self.pose(after), fraction)

    def _rows(self, columns=slice(None)):
        return np.frombuffer(self._values, dtype=float).reshape(-1, 7)[:, columns].copy()


def _lone(stamps, jump_ns):
    """
    Return which stamps (N,) belong to no timeline: a mask for RecordedStream.runs.

    One or two messages together, all more than jump_ns behind the message before them or
    all more than jump_ns ahead of the message after them, where the message after them is
    not behind the one before (the timeline resumes: a restart stays behind); a first
    message ahead of the second by more (a future stamp: a restart after one message would
    look the same, and one message pairs with nothing either way); a last one behind the
    last one kept before it (a stale stamp). A slow stream, its messages further apart than
    jump_ns, has none: they are neither behind nor ahead.
    """
    n = len(stamps)
    lone = np.zeros(n, dtype=bool)
    if n < 2:
        return lone
    for k in (1, 2):   # k messages i .. i + k - 1, between i - 1 and i + k
        if n < k + 2:
            break
        before, after = stamps[:n - k - 1], stamps[k + 1:]
        odd = [stamps[1 + j:n - k + j] for j in range(k)]
        behind = np.logical_and.reduce([o < before - jump_ns for o in odd])
        ahead = np.logical_and.reduce([o > after + jump_ns for o in odd])
        mark = (after >= before - jump_ns) & (behind | ahead)
        for j in range(k):
            lone[1 + j:n - k + j] |= mark
    after = np.flatnonzero(~lone[1:])   # (against the messages kept)
    if len(after) and stamps[0] > stamps[after[0] + 1] + jump_ns:
        lone[0] = True
    kept = np.flatnonzero(~lone[:-1])
    if len(kept) and stamps[kept[-1]] - stamps[-1] > jump_ns:
        lone[-1] = True
    return lone
