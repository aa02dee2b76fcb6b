"""
Checks of incoming pose messages: numbers in, verdicts out (no rclpy, no messages).

The live node skips every pose message it cannot use, counts it under (stream, reason),
and logs it (throttled per stream and reason) with the topic and the reason.  The reasons
(REASONS, codes used as /diagnostics keys such as bad_link_pose_zero_stamp) come from these
places, each checked once:

- this module: a zero header stamp, a stamp farther than max_stamp_offset_ns from the node
  clock (with use_sim_time that clock is /clock), a header frame_id other than the expected
  one of its stream, a position beyond max_position_m;
- conversions (BadPoseError, whose `reason` is one of these codes): NaN or inf, a zero
  quaternion, a quaternion whose norm is far from 1 (one slightly off is renormalised), an
  unusable covariance, a stamp whose nanosec is out of range, anything else not a pose
  ('malformed');
- the session (session.Rejected, whose `code` is one of these codes): a stamp older than the
  previous one of its stream, or the same stamp again;
- the readers of raw bytes (the node's fast path, the bag replay): bytes that do not decode
  ('undecodable'); the TF input (ros.tf_feed): a transform that would break the tree.

`StreamStats` keeps the counts, when each stream was last heard (node clock) and when it last
gave a usable pose, so the node can say which stream is stale.  Bad messages cost one
counter update each; the text of a reason is built only when it is logged.  Stamps are
integer nanoseconds.
"""

from collections import Counter
from dataclasses import dataclass
import math

import numpy as np
from quatcal_ros.core.units import MAX_POSITION_M, NS_PER_S, shown
from quatcal_ros.stream.log_throttle import LOG_THROTTLE_S, LogThrottle

LINK, SENSOR = 'link_pose', 'sensor_pose'
STREAMS = (LINK, SENSOR)
# A stream not heard (or without a usable pose) for this long, node clock, is stale.
STALE_AFTER_S = 3.0
# A value from a message (a frame id) is logged with at most this many characters.
MAX_LOGGED_CHARACTERS = 80

REASONS = {
    'non_finite': 'NaN or inf in the pose',
    'zero_quaternion': 'zero quaternion',
    'non_unit_quaternion': 'quaternion norm far from 1',
    'malformed': 'not a pose (wrong fields or values)',
    'bad_covariance': 'a pose covariance that is not finite, symmetric and positive definite, '
                      'or nearly singular',
    'bad_stamp': 'header stamp out of range',
    'zero_stamp': 'zero header stamp',
    'stamp_in_future': 'header stamp far in the future of the node clock',
    'stamp_in_past': 'header stamp far in the past of the node clock',
    'duplicate_stamp': 'same header stamp as the previous message',
    'out_of_order': 'header stamp older than the previous message',
    'stale_stamp': 'a header stamp far behind the stream, which the next message did not '
                   'follow: a stale message, not a time jump',
    'wrong_frame_id': 'header.frame_id is not the configured frame',
    'implausible_position': 'a position farther from the origin than max_position_m',
    'undecodable': 'recorded bytes that do not decode as the topic type',
    'breaks_tree': 'a transform that would break the TF tree (a loop, a second parent, an '
                   'empty frame id)',
}


@dataclass(frozen=True)
class CheckConfig:
    """
    What the node accepts; durations in integer nanoseconds.

    max_stamp_offset_ns: largest distance of a header stamp from the node clock; 0: any.
    link_frame_id, sensor_frame_id: the header.frame_id each stream must carry; '': any.
    """

    max_stamp_offset_ns: int = 30 * NS_PER_S
    link_frame_id: str = ''
    sensor_frame_id: str = ''
    max_position_m: float = MAX_POSITION_M

    def __post_init__(self):
        if self.max_stamp_offset_ns < 0:
            raise ValueError(f'max_stamp_offset_ns must be >= 0, not {self.max_stamp_offset_ns}')

    def frame_id(self, stream):
        """Return the header.frame_id expected on `stream` ('' accepts any)."""
        return self.link_frame_id if stream == LINK else self.sensor_frame_id


def stamp_reason(stamp_ns, now_ns, max_offset_ns):
    """
    Return why a header stamp cannot be used, or None when it can.

    'zero_stamp' for 0 (the publisher left it unset); 'stamp_in_future' or 'stamp_in_past'
    when it is more than max_offset_ns from now_ns (the node clock).  No clock check when
    max_offset_ns is 0 or the node clock has not started (now_ns <= 0: use_sim_time before
    the first /clock message).
    """
    if stamp_ns == 0:
        return 'zero_stamp'
    if max_offset_ns and now_ns > 0:
        if stamp_ns - now_ns > max_offset_ns:
            return 'stamp_in_future'
        if now_ns - stamp_ns > max_offset_ns:
            return 'stamp_in_past'
    return None


def stamps_usable(stamps_ns, now_ns, max_offset_ns):
    """Return which stamps (an int64 array) stamp_reason finds nothing wrong with (bool)."""
    usable = stamps_ns != 0
    if max_offset_ns and now_ns > 0:
        usable &= np.abs(stamps_ns - np.int64(now_ns)) <= max_offset_ns
    return usable


def frame_reason(frame_id, expected):
    """Return 'wrong_frame_id' when `expected` is set and `frame_id` differs, else None."""
    if not expected or frame_id == expected:
        return None
    # tf2 frame ids have no leading slash; ROS 1 habits add one.
    if frame_id.lstrip('/') == expected.lstrip('/'):
        return None
    return 'wrong_frame_id'


def check(stream, stamp_ns, frame_id, now_ns, config):
    """Return why a message of `stream` with this stamp and frame is bad, or None (cheap)."""
    reason = stamp_reason(stamp_ns, now_ns, config.max_stamp_offset_ns)
    if reason is None:
        reason = frame_reason(frame_id, config.frame_id(stream))
    return reason


def describe(reason, stream, stamp_ns=None, frame_id=None, now_ns=None, config=None):
    """
    Return the sentence logged for a bad message of `stream` that `check` refused.

    Built only when the throttled log is due: it says what was wrong and what to do.
    """
    if reason == 'zero_stamp':
        return 'header stamp is zero: the publisher must stamp its messages (exposure time)'
    if reason in ('stamp_in_future', 'stamp_in_past'):
        offset_s = (stamp_ns - now_ns) / NS_PER_S
        side = 'ahead of' if offset_s > 0 else 'behind'
        return (f'header stamp {stamp_ns / NS_PER_S:.3f} s is {abs(offset_s):.3g} s {side} the '
                f'node clock (limit {config.max_stamp_offset_ns / NS_PER_S:g} s, parameter '
                'max_stamp_offset_s): are the clocks synchronised? For a bag, play it with '
                '--clock and set use_sim_time; 0 turns the check off')
    if reason == 'wrong_frame_id':
        parameter = 'link_frame_id' if stream == LINK else 'sensor_frame_id'
        return (f'header.frame_id {shown(frame_id, MAX_LOGGED_CHARACTERS)!r} is not '
                f'{config.frame_id(stream)!r} (parameter {parameter}): is the topic remapped '
                'to the right source?')
    return REASONS.get(reason, reason)


def pose_error_reason(error):
    """Return the reason code of a conversions.BadPoseError (its `reason`, else 'malformed')."""
    reason = getattr(error, 'reason', '')
    return reason if reason in REASONS else 'malformed'


def rejected_reason(event):
    """Return the reason code of a session.Rejected pose (its `code`, else 'malformed')."""
    code = getattr(event, 'code', '')
    return code if code in REASONS else 'malformed'


def position_reason(position, config):
    """Return 'implausible_position' when a coordinate exceeds config.max_position_m."""
    limit = config.max_position_m
    if -limit <= position[0] <= limit and -limit <= position[1] <= limit and \
            -limit <= position[2] <= limit:
        return None
    return 'implausible_position'


def detail_text(detail):
    """Return the text of a bad message's detail (text, exception, or function building it)."""
    if detail is None:
        return ''
    return shown(detail() if callable(detail) else detail, 4 * MAX_LOGGED_CHARACTERS)


def diagnostic_key(stream, reason):
    """Return the /diagnostics key of a bad-message count, e.g. bad_link_pose_zero_stamp."""
    return f'bad_{stream}_{reason}'


def silent_input(stream, names, composed=()):
    """
    Say that `stream` has sent nothing yet, on its topic from `names` (stream: topic).

    A stream in `composed` is TF input: its poses are composed from frames on its topic, so
    that topic being silent and a frame name being wrong look the same here.
    """
    topic = names.get(stream, stream)
    if stream in composed:
        return (f'no pose composed from {topic} yet: are the frame names right, and does the '
                'publisher run?')
    return (f'no message on {topic} yet: is it remapped to the right topic, and does the '
            'publisher run?')


# StreamStats._sequence of a stream whose numbers went back: not counted until restarted.
_STOPPED = object()
# More messages a second than a publisher sends over DDS (a Python loop publishing as fast as
# it can reached about 20 kHz here): a gap larger than this rate allows is another
# publisher's numbers (one discovered late, numbered far ahead), not a loss.
MAX_PUBLISH_HZ = 1_000_000


def _possible(source_ns, last_source_ns):
    """Return how many messages a publisher can have sent between two of its stamps."""
    if source_ns is None or last_source_ns is None:
        return math.inf
    return MAX_PUBLISH_HZ * max(source_ns - last_source_ns, 0) / NS_PER_S


class StreamStats:
    """
    Messages per stream: received, usable, bad per reason; when last heard; log throttling.

    Times: node clock (now_ns) for staleness, steady clock (steady_ns) for log throttling.
    Every received message is either good (`note_good`) or bad (`note_bad`) exactly once,
    so received == good + bad for each stream, but for a pose the session holds undecided
    (session.Session.held: counted when decided). `lost` counts the messages a stream's
    publisher numbered but that never came (note_sequence), for the streams with one
    publisher (those with a count: restart_sequence).
    """

    def __init__(self, throttle_s=LOG_THROTTLE_S):
        self.received = Counter()
        self.good = Counter()
        self.bad = Counter()                # (stream, reason): count
        self._bad_before_session = Counter()  # `bad` when the session last started over
        self.first_ns = None
        self.last_ns = {}
        self.last_good_ns = {}
        self.last_bad = {}                  # stream: reason of its latest bad message
        self.first_detail = {}              # (stream, reason): detail of the first one
        self.lost = Counter()
        self._sequence = {}                 # stream: publication sequence number last seen
        self._source_ns = {}                # stream: its publisher's stamp of that message
        self._log = LogThrottle(int(throttle_s * NS_PER_S))   # per (stream, reason)

    def note(self, stream, now_ns, count=1):
        """Count `count` messages received on `stream` at node time now_ns."""
        self.received[stream] += count
        self.last_ns[stream] = now_ns
        if self.first_ns is None:
            self.first_ns = now_ns

    def note_sequence(self, stream, sequence, source_ns=None):
        """
        Count as lost the messages missing before publication sequence number `sequence`.

        The numbers of one publisher go up by one per message sent; a gap is messages that
        never reached the node (its queue overflowed, or the network dropped them). A number
        not above the last one (a publisher restarted, or a second one joined), or a gap
        more messages than MAX_PUBLISH_HZ could have sent in the publisher's time between
        the two (source_ns, its clock; a second publisher numbered far ahead), stops the
        count until `restart_sequence`.
        """
        last = self._sequence.get(stream)
        if last is _STOPPED:
            return
        if last is not None and (sequence <= last or sequence - last - 1 > _possible(
                source_ns, self._source_ns.get(stream))):
            self._sequence[stream] = _STOPPED
            return
        self._sequence[stream] = sequence
        self._source_ns[stream] = source_ns
        if last is not None and sequence > last + 1:
            self.lost[stream] += sequence - last - 1

    def restart_sequence(self, stream, always=True):
        """
        Count `stream`'s losses from its next number on (not always: only if stopped).

        Call it when the stream's publishers change; `lost` then holds a count for it.
        """
        if always or self._sequence.get(stream) is _STOPPED:
            self._sequence.pop(stream, None)
        self.lost[stream] += 0

    def note_good(self, stream, now_ns, count=1):
        """Count `count` messages of `stream` that reached the session."""
        self.good[stream] += count
        self.last_good_ns[stream] = now_ns

    def note_bad(self, stream, reason, steady_ns, detail=None):
        """
        Count a skipped message; return how many to report when a log line is due, else None.

        The first bad message of a (stream, reason) is logged at once, later ones at most
        every throttle_s: the number returned counts them all since the previous log line.
        detail: its explanation (text, exception, or a function that builds it); the first
        one of each (stream, reason) is kept (`example`).
        """
        key = (stream, reason)
        self.bad[key] += 1
        self.first_detail.setdefault(key, detail)
        self.last_bad[stream] = reason
        return self._log.due(key, steady_ns)

    def start_session(self):
        """
        Start counting `bad_in_session` from zero (the session started over: ~/reset).

        The examples (`example`) start over too: each is then the session's first.
        """
        self._bad_before_session = Counter(self.bad)
        self.first_detail = {}

    def bad_in_session(self):
        """Return the bad messages per (stream, reason) since `start_session`."""
        return self.bad - self._bad_before_session

    def example(self, stream, reason):
        """Return the text of the first bad message of (stream, reason), or ''."""
        return detail_text(self.first_detail.get((stream, reason)))

    @property
    def bad_total(self):
        """Return the number of bad messages on all streams."""
        return sum(self.bad.values())

    def bad_of(self, stream):
        """Return the number of bad messages on `stream`."""
        return sum(n for (s, _), n in self.bad.items() if s == stream)

    def stale(self, now_ns, after_s=STALE_AFTER_S):
        """Streams not heard for after_s (node clock) since the first message of either."""
        return [stream for stream, _ in self.stale_reasons(now_ns, after_s)]

    def stale_reasons(self, now_ns, after_s=STALE_AFTER_S, started_ns=None, names=None,
                      composed=()):
        """
        Return [(stream, 'sensor_pose stale: no message for 4.2 s'), ...] (node clock).

        The topic is named where its name is not the stream's ('no message on
        /camera/image_raw': images, or a remapped topic).

        A stream is stale when it has sent nothing, or nothing usable, for after_s.  Before
        the first message of any input, a stream is named only when `started_ns` (when
        the listening began) is given and after_s have passed since: 'no message on TOPIC
        yet', TOPIC from `names` (stream: topic), with the likely cause.  Streams in
        `composed` are TF input: poses composed from frames on their topic, said so (the
        topic's own messages count as input: /tf may be busy while a frame never comes).
        """
        names = names or {}
        if self.first_ns is None:
            if started_ns is None or now_ns - started_ns < int(after_s * NS_PER_S):
                return []
            return [(stream, silent_input(stream, names, composed)) for stream in STREAMS]
        limit = now_ns - int(after_s * NS_PER_S)
        out = []
        for stream in STREAMS:
            last = self.last_ns.get(stream)
            # The topic, where its name is not the stream's (remapped, or camera images).
            topic = names.get(stream, stream)
            on = '' if topic.rstrip('/').rsplit('/', 1)[-1] == stream else f' on {topic}'
            what = (f'no pose composed from {topic}' if stream in composed
                    else f'no message{on}')
            if last is None:
                age_s = (now_ns - self.first_ns) / NS_PER_S
                if self.first_ns < limit:
                    at_all = '' if stream in composed else ' at all'
                    out.append((stream, f'{stream} stale: {what}{at_all} in {age_s:.1f} s'))
                continue
            if last < limit:
                out.append((stream, f'{stream} stale: {what} for '
                                    f'{(now_ns - last) / NS_PER_S:.1f} s'))
                continue
            last_good = self.last_good_ns.get(stream, self.first_ns)
            if last_good < limit:
                reason = self.last_bad.get(stream, '')
                out.append((stream, f'{stream} stale: no usable message{on} for '
                                    f'{(now_ns - last_good) / NS_PER_S:.1f} s (bad messages '
                                    f'only, latest: {REASONS.get(reason, reason)})'))
        return out
