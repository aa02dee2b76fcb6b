"""
The calibrator's status on /diagnostics: state, counts, quality, and every problem in words.

`calibrator_status` builds one diagnostic_msgs/DiagnosticStatus from the session, the message
counts (message_checks.StreamStats) and the problems the node knows of (a moved marker, a
journal that cannot be written, a publish_tf that would break the TF tree).  The level is
WARN when there is any problem: a stale stream, a high residual, the estimator's warnings, or
those given.
"""

from diagnostic_msgs.msg import DiagnosticStatus
from diagnostic_msgs.msg import KeyValue
import numpy as np
from quatcal_ros.core import conventions, quaternion as quat
from quatcal_ros.core.validation import failure_warning
from quatcal_ros.stream import message_checks
from quatcal_ros.stream.capture import unsteady_sensor_note
from quatcal_ros.stream.message_checks import LINK, SENSOR, STALE_AFTER_S
from quatcal_ros.stream.session import TOPICS as SESSION_TOPICS
from quatcal_ros.stream.session import UNPAIRED_NOTICE_AFTER
from rclpy.qos import ReliabilityPolicy


def status_name(node_name):
    """Return the DiagnosticStatus name of a calibrator node: two on one domain differ."""
    return f'{node_name}: hand-eye rotation'


DIAGNOSTIC_NAME = status_name('calibrator')   # the default node's
# An RMS motion residual above this (degrees) means inconsistent data: WARN.
HIGH_RESIDUAL_DEG = 1.0
# Seconds of paired poses without a still sample (auto capture) after which that is a
# problem (WARN): a stop-and-go session stops every few seconds.
NEVER_STILL_S = 30.0
# ... and after which the status suggests continuous capture (not in a robot's first motion).
NEVER_STOPS_HINT_S = 10.0
# Messages lost between two statuses (StreamStats.lost) that are a problem: at least this
# many, and this fraction of those sent. The pairing interpolates across a few missing link
# poses; a steady loss means the node or the network cannot keep up.
LOST_MESSAGES = 10
LOST_FRACTION = 0.01
# Clock jumps back within one status period that point to two clocks on one stream.
REPEATED_JUMPS = 3
# The session's count of each stream's poses (Session.counters: its stream name + _messages).
SESSION_COUNTERS = {topic: f'{stream}_messages' for stream, topic in SESSION_TOPICS.items()}


def format_quaternion_xyzw(q_wxyz):
    """'x, y, z, w = (..)' text of a quaternion given as (w, x, y, z)."""
    x, y, z, w = quat.xyzw_from_wxyz(q_wxyz)
    return f'x, y, z, w = ({x:.6f}, {y:.6f}, {z:.6f}, {w:.6f})'


def describe_result(result):
    """One log line for a new estimate: the rotation, the translation, their uncertainties."""
    translation, uncertainty = '', f'{result.uncertainty_deg:.3f} deg'
    if result.translation is not None:
        x, y, z = (float(v) for v in result.translation)
        translation = f', translation ({x:.4f}, {y:.4f}, {z:.4f}) m'
        uncertainty += f' and {result.translation_uncertainty_mm:.2f} mm'
    return (f'estimate: {format_quaternion_xyzw(result.quaternion)}{translation}, residual '
            f'{result.residual_rms_deg:.3f} deg RMS, uncertainty {uncertainty}, from '
            f'{result.samples} samples ({result.inliers} of {result.motions} motions used)'
            f'{"" if result.usable else "; it says not to use it (usable false: its warnings)"}'
            f'; next: {result.hint}')


class InputWatch:
    """
    Problems of the node's input that no single message shows, found at each status.

    On a silent or stale stream, publishers of the wrong type, or only best-effort ones when it is
    subscribed reliable (which hears no best-effort publisher); clock jumps that point to two
    clocks on one stream; use_sim_time without /clock or with a /clock that stopped; and when
    listening began (for silent streams).
    """

    def __init__(self, expected_types, started_ns, reliable=()):
        self.expected_types = expected_types   # {stream: 'geometry_msgs/msg/PoseStamped'}
        self.reliable = frozenset(reliable)    # the streams subscribed reliable
        self.started_ns = started_ns
        self.jumps_seen = 0                  # the session's time jumps at the last status
        self.stale_seen = 0                  # and its stale-stamped messages
        self.clock_seen = (None, None)       # (node clock, steady clock) when it last moved
        self.counts_seen = {}                # stream: (received, lost) at the last status
        # streams whose silence the publishers' type or QoS explains (at the last status): the
        # silent stream's 'is it remapped ..., does the publisher run?' would mislead
        self.explained = frozenset()

    def problems(self, stats, topics, publishers, time_jumps, now_ns, sim_time,
                 steady_ns=None):
        """
        Return the problems in words, given the counts and the graph at node time now_ns.

        publishers(topic): the topic's publishers in the ROS graph (rclpy's
        TopicEndpointInfo: topic_type, qos_profile);
        steady_ns: the steady (wall) clock, to see a node clock that stopped.
        """
        found, explained = [], set()
        stale = set(stats.stale(now_ns))   # a publisher replaced after the stream had data
        for stream, topic in topics.items():
            if stats.received[stream] and stream not in stale:
                continue
            expected = self.expected_types[stream]
            heard = publishers(topic)
            wrong = sorted({info.topic_type for info in heard} - {expected})
            if wrong:
                explained.add(stream)
                found.append(f'{topic} has publishers of type {", ".join(wrong)}; the node '
                             f'subscribes {expected} (parameter pose_type'
                             f'{", or sensor_pose_type" if stream == "sensor_pose" else ""})')
            elif heard and stream in self.reliable and all(
                    info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                    for info in heard):
                explained.add(stream)
                found.append(f'{topic} has only best-effort publishers ({len(heard)}); the '
                             'node subscribes it reliable, and a reliable subscription hears '
                             "no best-effort publisher: publish it reliable (the driver's QoS "
                             'setting, or a relay)')
        self.explained = frozenset(explained)
        for stream, topic in topics.items():
            received, lost = stats.received[stream], stats.lost[stream]
            before = self.counts_seen.get(stream, (0, 0))
            self.counts_seen[stream] = (received, lost)
            new_lost, sent = lost - before[1], received - before[0] + lost - before[1]
            if new_lost >= LOST_MESSAGES and new_lost > LOST_FRACTION * sent:
                found.append(f'{topic}: {new_lost} of the {sent} messages sent since the last '
                             f'status ({100.0 * new_lost / sent:.1f} %) were lost before the '
                             'node read them: its queue overflowed (the node falls behind: '
                             'CPU load) or the network dropped them')
        # a second clock's messages are time jumps, or stale messages when they are sparse
        stale = sum(stats.bad[(stream, 'stale_stamp')] for stream in topics)
        jumps, behind = time_jumps - self.jumps_seen, stale - self.stale_seen
        if jumps + behind >= REPEATED_JUMPS:
            found.append(f'the stamps jumped back {jumps + behind} times since the last status'
                         f'{f" ({behind} single messages far behind, dropped)" if behind else ""}'
                         ': two publishers with different clocks on one stream? (ros2 topic '
                         'info -v link_pose / sensor_pose)')
        self.jumps_seen, self.stale_seen = time_jumps, stale
        if now_ns <= 0 and sim_time:
            found.append('use_sim_time is true but no /clock message has come: no clock runs '
                         '(play the bag with --clock, or start the simulator)')
        elif sim_time and steady_ns is not None:
            if now_ns != self.clock_seen[0]:
                self.clock_seen = (now_ns, steady_ns)
            elif steady_ns - self.clock_seen[1] > STALE_AFTER_S * 1e9:
                found.append(f'use_sim_time is true and /clock has stood at {now_ns * 1e-9:.3f} s '
                             f'for {(steady_ns - self.clock_seen[1]) * 1e-9:.0f} s: is the '
                             'bag paused, or its player or the simulator stopped?')
        if self.started_ns <= 0:   # use_sim_time: listening begins with the clock
            self.started_ns = now_ns
        return found


def skipped_text(stats, stream=None):
    """
    Return 'N bad messages skipped, most for REASON on STREAM, the first: WHY', or ''.

    Of `stream` alone when given, since the session started (~/reset starts over); WHY is
    the first such message's explanation (its hint). When STREAM's latest bad message had
    another reason, '; the latest for REASON' follows: a cause fixed long ago (a camera_info
    that came late) stayed the only one named.
    """
    counts = [(key, n) for key, n in stats.bad_in_session().most_common()
              if stream in (None, key[0])]
    if not counts:
        return ''
    (where, reason), _ = counts[0]
    example = stats.example(where, reason)
    latest = stats.last_bad.get(where)
    return (f'{sum(n for _, n in counts)} bad messages skipped, most for {reason} on {where}'
            f'{f", the first: {example}" if example else ""}'
            f'{f"; the latest for {latest}" if latest and latest != reason else ""}')


def status_message(session, stats, topics=None, composed=(), result=None):
    """
    Describe the state in operator words; `topics` (stream: resolved topic) names them.

    Streams in `composed` are TF input (poses composed from frames on their topic); `result`
    the published estimate when it is not the session's (on pixels).
    """
    result = result or session.result
    if result is not None:
        return f'estimating: uncertainty {result.uncertainty_deg:.2g} deg'
    if session.state == 'waiting for poses':
        topics = topics or {}
        silent = [s for s in (LINK, SENSOR) if not stats.received[s]]
        parts = []
        from_tf = [s for s in silent if s in composed]
        if from_tf:   # /tf itself may be busy: its frames do not compose
            parts.append(f'no {" or ".join(from_tf)} composed from {topics.get(from_tf[0])} '
                         'yet')
        quiet = [topics.get(s, s) for s in silent if s not in composed]
        if quiet:
            parts.append(f'nothing on {" and ".join(quiet)} yet')
        if parts:
            return f'waiting for poses ({", and ".join(parts)})'
        skipped = skipped_text(stats)
        if skipped:
            return f'waiting for poses ({skipped})'
        counters = session.counters   # since the session (re)started: ~/reset clears them
        idle = [topics.get(s, s) for s in (LINK, SENSOR)
                if not counters[SESSION_COUNTERS[s]]]
        if idle:   # (the stats count messages since the node started)
            return (f'waiting for poses (no pose from {" or ".join(dict.fromkeys(idle))} since '
                    'the session started)')
        return 'waiting for poses (none paired yet: are both stamped on the same clock?)'
    count, capture = len(session.samples), session.config.capture
    if count == 0 and capture.mode == 'auto':   # paired poses, yet no still window
        return (f'collecting: no still sample yet from {session.counters["pairs"]} paired '
                f'poses: {still_advice(session)}')
    return f'collecting: {count} sample(s), need motions about 2 different axes'


def still_advice(session):
    """Say how auto capture gets a still sample: the stops, the sensor bands, continuous."""
    capture, unsteady = session.config.capture, session.counters['unsteady_sensor']
    sensor = unsteady_sensor_note(unsteady, capture,
                                  ('sensor_still_rotation_deg', 'sensor_still_translation_m'),
                                  session.sensor_scatter)
    # (not when the link stood still: the robot stops, the sensor is what moves)
    never = ('; a robot that never stops needs capture_mode continuous'
             if session.paired_seconds >= NEVER_STOPS_HINT_S and not unsteady else '')
    return (f'stop the robot at each pose for {capture.window_ns * 1e-9:g} s (still_window_s) '
            f'after each motion{sensor}{never}')


def never_still(session):
    """Return the problem of auto capture without a still sample for NEVER_STILL_S, or None."""
    if (session.result is None and not session.counters['samples']
            and session.config.capture.mode == 'auto'
            and session.paired_seconds >= NEVER_STILL_S):
        return f'no still sample in {session.paired_seconds:.0f} s of paired poses'
    return None


def calibrator_status(session, stats, now_ns, hardware_id, problems=(), tf_static='',
                      started_ns=None, topics=None, next_pose=None, result=None, composed=(),
                      name=DIAGNOSTIC_NAME, explained=()):
    """
    Return the DiagnosticStatus of the calibrator.

    :param problems: further problems to name (texts); each makes the level WARN.
    :param tf_static: the /tf_static broadcast state, in words.
    :param started_ns: when the node began to listen (node clock): a stream that never sent
        anything is named after STALE_AFTER_S, with `topics` (stream: resolved topic).
    :param next_pose: the planner's core.planner.NextPose, or None.
    :param result: the published CalibrationResult when it is not the session's (on pixels).
    :param composed: the streams of TF input (poses composed from frames on their topic).
    :param explained: streams whose silence a problem already explains (InputWatch): their
        stale text is left out (the stream stays in the 'stale' key).
    """
    result = result or session.result
    counters = session.counters
    stale = stats.stale_reasons(now_ns, STALE_AFTER_S, started_ns, topics, composed)
    found = list(dict.fromkeys(text for stream, text in stale   # (TF input: one topic, /tf)
                               if stream not in explained))
    # The input's problems before the estimate's warnings: they are the causes (swapped TF
    # frames make the frame-convention warning advise another setup).
    found += [text for text in problems if text]
    if result is not None and result.residual_rms_deg > HIGH_RESIDUAL_DEG:
        found.append(f'high residual {result.residual_rms_deg:.2f} deg RMS: check the frame '
                     'conventions and the time alignment of the streams')
    # 'not checked yet' (3 samples) is the state of the frame-convention check, no problem
    notes = [w for w in (result.warnings if result is not None else [])
             if conventions.unchecked([w])]
    if result is not None:
        found += [w for w in result.warnings if w not in notes]
    validation = (result.validation if result is not None else None) or {}
    on_pixels = (result.reprojection if result is not None else None) or {}
    failed = failure_warning(validation)
    found += [failed] if failed else []
    stuck = never_still(session)
    found += [stuck] if stuck else []
    if not counters['pairs'] and counters['unpaired'] >= UNPAIRED_NOTICE_AFTER:
        found.append(f'none of {counters["unpaired"]} poses could be paired; the latest: '
                     f'{session.last_unpaired}')
    values = {
        'state': session.state,
        'samples': counters['samples'],
        'motions': result.motions if result is not None else counters['motions'],
        'inliers': result.inliers if result is not None else 0,
        'residual_rms_deg': _number_text(result and result.residual_rms_deg),
        'uncertainty_deg': _number_text(result and result.uncertainty_deg),
        'method': result.method if result is not None else '',
        'translation_xyz_m': (' '.join(f'{v:.6f}' for v in result.translation)
                              if result is not None else ''),
        'translation_uncertainty_mm': _number_text(result and result.translation_uncertainty_mm),
        # the fit on the pixels (image input): the corners' noise, each view's shared error
        'pixel_noise_px': _number_text(on_pixels.get('pixel_noise_px')),
        'view_error_deg': ' '.join(f'{v:.3g}' for v in on_pixels.get('view_error_deg', ())),
        'view_error_mm': ' '.join(f'{v:.3g}' for v in on_pixels.get('view_error_mm', ())),
        'focal_scale': _number_text(on_pixels.get('focal_scale')),
        'validation': validation.get('verdict', ''),
        'validation_rms_rotation_deg': _number_text(validation.get('rms_rotation_deg')),
        'validation_rms_translation_mm': _number_text(validation.get('rms_translation_mm')),
        'validation_rms_reprojection_px': _number_text(validation.get('rms_reprojection_px')),
        'validation_worst_samples': ' '.join(str(w['sample'])
                                             for w in validation.get('worst', [])),
        'tf_static': tf_static,
        'hint': result.hint if result is not None else session.last_error,
        'next_pose': _next_pose_text(next_pose),
        'link_messages': stats.received[LINK],
        'sensor_messages': stats.received[SENSOR],
        # sent by the stream's one publisher but never received (publication sequence gaps);
        # '' where not counted (TF input, images, two publishers from the start)
        'link_messages_lost': stats.lost.get(LINK, ''),
        'sensor_messages_lost': stats.lost.get(SENSOR, ''),
        'bad_messages': stats.bad_total,
        'stale': ' '.join(stream for stream, _ in stale),
        'paired_poses': counters['pairs'],
        'rejected_messages': counters['rejected'],
        # Clock jumps back (a bag played again): each restarted the pairing; stills that
        # repeat earlier samples after one are not added twice.
        'time_jumps': counters['time_jumps'],
        'repeated_samples': counters['repeated_samples'],
        'sensor_jumps': counters['sensor_jumps'],   # left out of still samples (a flip)
    }
    for (stream, reason), count in sorted(stats.bad.items()):
        values[message_checks.diagnostic_key(stream, reason)] = count
    return DiagnosticStatus(
        level=DiagnosticStatus.WARN if found else DiagnosticStatus.OK, name=name,
        message='; '.join([status_message(session, stats, topics, composed, result)] + notes
                          + found),
        hardware_id=hardware_id,
        values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])


def _next_pose_text(next_pose):
    """Return the proposed link pose in words: position, quaternion, the expected gain."""
    if next_pose is None:
        return ''
    x, y, z, w = quat.xyzw_from_wxyz(next_pose.link.quaternion)
    position = ' '.join(f'{v:.4f}' for v in next_pose.link.position)
    return (f'position {position} m, quaternion (x, y, z, w) {x:.5f} {y:.5f} {z:.5f} {w:.5f}; '
            f'expected uncertainty {next_pose.uncertainty_deg:.4f} deg, '
            f"{next_pose.translation_uncertainty_mm:.3f} mm (the model's figures: now "
            f'{next_pose.current_uncertainty_deg:.4f} deg, '
            f'{next_pose.current_translation_uncertainty_mm:.3f} mm; the reported uncertainty '
            'is measured over the samples)')


def _number_text(value):
    if value is None or value is False:
        return ''
    return f'{float(value):.6g}' if np.isfinite(value) else 'nan'
