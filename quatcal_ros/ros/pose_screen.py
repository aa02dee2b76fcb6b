"""
Pose messages in: checked, converted and counted, one way for the live node and the replay.

`PoseScreen.take(stream, msg, now_ns)` runs the checks of message_checks (header stamp, frame
id) and of conversions (numbers, quaternion) on one stamped pose or transform message, cheapest
first, and returns (stamp_ns, Pose) or None.  `verdict` takes the session's events for that
pose and counts the session's own refusals (a stamp out of order or repeated, a stale one).
Every message is counted exactly once, good or bad, a pose the session holds undecided when
it is decided (`stats`, message_checks.StreamStats); a bad one is
reported through `on_bad` when its throttled report is due, with the text built only then.
The replay reports nothing while it runs (on_bad None) and lists the counts at the end.
"""

import time

from quatcal_ros.ros.conversions import BadPoseError, pose_from_msg, stamp_ns_from_header
from quatcal_ros.stream import message_checks
from quatcal_ros.stream.log_throttle import LOG_THROTTLE_S
from quatcal_ros.stream.message_checks import CheckConfig, STREAMS, StreamStats
from quatcal_ros.stream.session import Rejected


class PoseScreen:
    """The checks and the counts of the pose messages of a session's streams."""

    def __init__(self, config=CheckConfig(), on_bad=None,
                 throttle_s=LOG_THROTTLE_S):
        """
        Check against `config` and report bad messages to `on_bad`.

        :param config: message_checks.CheckConfig, what the messages must satisfy.
        :param on_bad: on_bad(stream, reason, count, detail) when a bad message's report is
            due: count bad messages of (stream, reason) since the last report, detail the
            explanation (text, an exception, or a function that builds it).
        """
        self.config = config
        self.on_bad = on_bad
        self.stats = StreamStats(throttle_s)
        self._held = frozenset()   # the session's undecided poses at the last verdict

    def take(self, stream, msg, now_ns=0):
        """
        Return (stamp_ns, Pose) of `msg` on `stream`, or None (then it is counted as bad).

        now_ns: the node clock (0 offline: no clock check).
        """
        stamp_ns = self.take_header(stream, msg.header, now_ns)
        if stamp_ns is None:
            return None
        try:
            pose = pose_from_msg(msg)
        except BadPoseError as error:
            self.bad(stream, message_checks.pose_error_reason(error), error)
            return None
        return self.placed(stream, stamp_ns, pose)

    def take_decoded(self, stream, stamp_ns, frame_id, pose, now_ns=0):
        """
        Return (stamp_ns, Pose) of a message a fast decoder read (cdr.decode_pose), or None.

        The checks and counts of `take` on the decoded stamp, frame id and pose, whose
        numbers conversions.pose_from_values already accepted.
        """
        self.stats.note(stream, now_ns)
        if not self._header_ok(stream, stamp_ns, frame_id, now_ns):
            return None
        return self.placed(stream, stamp_ns, pose)

    def placed(self, stream, stamp_ns, pose):
        """Return (stamp_ns, pose), or None (counted) when the position is implausibly far."""
        if message_checks.position_reason(pose.position, self.config) is not None:
            limit = self.config.max_position_m
            self.bad(stream, 'implausible_position', lambda: (
                f'position {pose.position.tolist()} m is farther than {limit:g} m from the '
                'origin (parameter max_position_m): are the units metres?'))
            return None
        return stamp_ns, pose

    def take_header(self, stream, header, now_ns=0):
        """
        Count one message of `stream` and check its header; return its stamp_ns or None.

        The checks of `take` before the pose: stamp and frame id (an image's header, too).
        """
        self.stats.note(stream, now_ns)
        try:
            stamp_ns = stamp_ns_from_header(header)
        except ValueError as error:   # nanosec out of range
            self.bad(stream, 'bad_stamp', error)
            return None
        return stamp_ns if self._header_ok(stream, stamp_ns, header.frame_id, now_ns) else None

    def _header_ok(self, stream, stamp_ns, frame_id, now_ns):
        """Return whether the stamp and frame id pass message_checks.check (else counted)."""
        reason = message_checks.check(stream, stamp_ns, frame_id, now_ns, self.config)
        return self._passed(stream, reason, stamp_ns, frame_id, now_ns)

    def stamp_ok(self, stream, stamp_ns, now_ns):
        """Return whether a stamp passes message_checks.stamp_reason (else counted)."""
        reason = message_checks.stamp_reason(stamp_ns, now_ns, self.config.max_stamp_offset_ns)
        return self._passed(stream, reason, stamp_ns, None, now_ns)

    def _passed(self, stream, reason, stamp_ns, frame_id, now_ns):
        """Return whether `reason` is None; else count the message bad, described when due."""
        if reason is None:
            return True
        config = self.config
        self.bad(stream, reason, lambda: message_checks.describe(
            reason, stream, stamp_ns, frame_id, now_ns, config))
        return False

    def take_rows(self, stream, count, now_ns=0):
        """Count `count` messages of `stream` that a fast decoder checked and found good."""
        self.stats.note(stream, now_ns, count)

    def verdict(self, stream, events, now_ns=0, count=1, held=frozenset()):
        """
        Count the session's verdict on `count` poses of `stream`; return the other events.

        Each Rejected of a pose stream (out of order, duplicate stamp, stale) is one bad pose
        of that stream. held: the streams whose last pose the session holds undecided after
        these poses (Session.held): such a pose is counted once decided, good unless rejected,
        so every pose is counted once: good = given + decided - rejected.
        """
        if not events and not held and not self._held:   # the usual pose: taken
            if count:
                self.stats.note_good(stream, now_ns, count)
            return events
        refused = [e for e in events if isinstance(e, Rejected) and e.what in STREAMS]
        for event in refused:
            self.bad(event.what, message_checks.rejected_reason(event), event.reason)
        for name in STREAMS:
            good = ((count if name == stream else 0) + (name in self._held) - (name in held)
                    - sum(e.what == name for e in refused))
            if good > 0:
                self.stats.note_good(name, now_ns, good)
        self._held = held
        if not refused:
            return events
        return [e for e in events if not (isinstance(e, Rejected) and e.what in STREAMS)]

    def bad(self, stream, reason, detail):
        """Count a bad message of `stream`; report it through on_bad when that is due."""
        count = self.stats.note_bad(stream, reason, time.monotonic_ns(), detail)
        if count is not None and self.on_bad is not None:
            self.on_bad(stream, reason, count, detail)
