"""
Has the marker or the sensor moved during the session?  A change point in the samples.

With the estimate q_z, every sample gives the fixed object's orientation in the base frame,
Z_i = link_i (x) q_z (x) sensor_i (motions.SampleRotations.object_orientations); for a good
session all Z_i agree up to the noise.  When the marker is bumped, or the sensor slips on its
mount, every later sample disagrees with the earlier ones: its residual (the angle between Z_i
and the mean of the samples before) rises well above the noise of those samples, and stays
there.  A bad detection (a marker flip) is a single sample; a move is a run of them that lasts
to the end.  The robust estimator rejects the moved samples as bad detections while they are
few (and the earlier ones once they are many), so the RMS residual alone does not show a move.

`find_move` looks for the earliest sample k (at least MIN_BEFORE samples in) from which on
every sample (at least RECENT of them) lies farther than RISE_FACTOR times the median residual
of the samples before k (and at least MIN_RISE_DEG) from their mean.  Isolated bad detections
among the samples before are left out of their mean and noise level.  For good samples the
residual angle follows sigma times a chi distribution with 3 degrees of freedom: a sample beyond
4 medians (6.2 sigma) has odds below 1e-7, so RECENT of them in a row do not happen by chance.
A move lasts: `came_back` tells when the last RECENT samples agree with those before it again
(noisier samples for a while, such as samples taken while moving in continuous capture).

Quaternions are (w, x, y, z).  No rclpy here.
"""

from dataclasses import dataclass

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.motions import SampleRotations

RECENT = 3            # samples after the change point needed to call it a move
MIN_BEFORE = 5        # samples before it needed for a noise level
RISE_FACTOR = 4.0     # residual rise, in medians of the residuals before
MIN_RISE_DEG = 0.05   # smallest residual counted as a rise (noise-free data)
# find_move examines at most this many change points, each O(N): of a longer file every
# step-th, then bisects between the one found and the one before (solve and replay over a
# file of 8,000 samples had taken 12 s here; 1,000 samples 0.3 s).
SCANNED = 500


@dataclass(frozen=True)
class Move:
    """A change point: samples from `first` on disagree with those before."""

    first: int            # index of the first sample after the move
    samples: int          # samples from `first` on
    before_deg: float     # median residual of the samples before
    after_deg: float      # median residual of the samples from `first` on
    threshold_deg: float  # what counted as a rise

    def text(self, continuous_from=None, offline=False):
        """
        Return the operator message: what rose, and what to do.

        continuous_from: the sample from which on capture was continuous, when the rise
        starts there (samples taken while moving are noisier: said first). offline: for a
        file's samples (solve, replay), where no ~/reset is to call.
        """
        rose = (f'the residual rose from {self.before_deg:.2f} to {self.after_deg:.2f} deg '
                f'over the last {self.samples} samples (from sample {self.first} on')
        if continuous_from is not None:
            return (f'{rose}, where capture_mode became continuous at sample {continuous_from}):'
                    ' samples taken while moving are noisier than still ones, the more so with '
                    'a time offset between the streams (sensor_time_offset_s). If nothing '
                    'moved, this passes once still samples come again (capture_mode auto); if '
                    'the marker or the sensor moved, call ~/reset and recollect')
        if offline:
            return (f'{rose}): has the marker or the sensor moved? solve the samples from '
                    f'sample {self.first} on, or record again')
        return (f'{rose}): has the marker or the sensor moved? call ~/reset and recollect '
                f'(offline: solve the samples from sample {self.first} on, or record again)')


def residual_angles(Z, center):
    """Angles (radians) between each orientation Z (N, 4) and `center` (4,)."""
    return quat.angle_between(np.broadcast_to(center, Z.shape), Z)


def robust_center(Z):
    """
    Mean orientation of Z (N, 4) and the residual angles of its consistent part (radians).

    Samples beyond RISE_FACTOR medians of the residuals (isolated bad detections) are left
    out of the mean, twice over.
    """
    keep = np.ones(len(Z), dtype=bool)
    for _ in range(3):
        center = quat.average(Z[keep])
        angles = residual_angles(Z, center)
        limit = max(RISE_FACTOR * np.median(angles[keep]), np.radians(MIN_RISE_DEG))
        keep = angles <= limit
        if keep.sum() < 2:
            keep = angles <= np.median(angles)
    center = quat.average(Z[keep])
    return center, residual_angles(Z[keep], center)


def came_back(samples, move, q_z, setup='eye_in_hand', invert_sensor=False, recent=RECENT):
    """
    Return whether the last `recent` samples after `move` agree with those before it again.

    Within find_move's threshold of the samples before the move (under the estimate q_z now):
    then the rise did not last, and it was no move.
    """
    if len(samples) - move.first < move.samples + recent:   # (not the move's own samples)
        return False
    Z = SampleRotations.from_samples(samples, setup, invert_sensor).object_orientations(
        np.asarray(q_z, dtype=float))
    center, _, threshold = _before(Z[:move.first])
    return bool(np.all(residual_angles(Z[-recent:], center) <= threshold))


def _before(Z):
    """Return the samples before a change point: their center, noise level, rise threshold."""
    center, residuals = robust_center(Z)
    level = float(np.median(residuals))
    return center, level, max(RISE_FACTOR * level, np.radians(MIN_RISE_DEG))


def find_move(samples, q_z, setup='eye_in_hand', invert_sensor=False, first=0,
              recent=RECENT, min_before=MIN_BEFORE):
    """
    Return the earliest Move in `samples` (list of pose.Sample), or None.

    :param q_z: the current estimate (w, x, y, z).
    :param setup: 'eye_in_hand' or 'eye_to_hand' (as the estimate was made).
    :param invert_sensor: as the estimate was made.
    :param first: look only for change points at or after this sample index (a caller that
        checks after every new sample passes the count checked before, less `recent`).
    :param recent: samples after the change point needed.
    :param min_before: samples before it needed.
    """
    n = len(samples)
    if n < min_before + recent:
        return None
    Z = SampleRotations.from_samples(samples, setup, invert_sensor).object_orientations(
        np.asarray(q_z, dtype=float))
    start, last = max(first, min_before), n - recent
    step = -(-(last + 1 - start) // SCANNED)   # (ceiling)
    if step <= 1:   # every change point: the node after each sample, a file of a few hundred
        return _earliest(Z, range(start, last + 1))
    # A longer file: every step-th change point (each costs O(N)), then the earliest between
    # the one found and the one before it (a move lasts, so it shows from both sides).
    found = _earliest(Z, range(last - (last - start) // step * step, last + 1, step))
    if found is None:
        return None
    low, high = max(start, found.first - step + 1) - 1, found.first
    while high - low > 1:
        middle = (low + high) // 2
        move = _move_at(Z, middle)
        if move is None:
            low = middle
        else:
            found, high = move, middle
    return found


def _earliest(Z, change_points):
    """Return the Move of the earliest of `change_points` that has one, or None."""
    return next(filter(None, (_move_at(Z, k) for k in change_points)), None)


def _move_at(Z, k):
    """Return the Move of change point k in the object orientations Z (N, 4), or None."""
    center, level, threshold = _before(Z[:k])
    after = residual_angles(Z[k:], center)
    if not np.all(after > threshold):
        return None
    return Move(first=k, samples=len(Z) - k, before_deg=float(np.degrees(level)),
                after_deg=float(np.degrees(np.median(after))),
                threshold_deg=float(np.degrees(threshold)))
