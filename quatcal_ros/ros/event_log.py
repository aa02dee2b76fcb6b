"""
What the live node says in its log about the session: samples, estimates, refusals, files.

`EventLog.log(events, move_check)` writes one line per session event (stream/session.py):
a captured sample with its link position, each estimate (diagnostics.describe_result) with
the samples newly rejected since the last one and its warnings, throttled refusals (of
poses, and of ~/capture: capture_refused) and notices, and the moved-marker check's messages
that `move_check(result)` returns. `messages` writes the (level, text) pairs of the journal and
the result files.

An estimate's warnings come back with every estimate: each is logged in full when it comes
(numbers aside: a warning whose numbers changed is the same), then, while every estimate
repeats it, shortened ('still: ...') at most every WARNING_REPEAT_S seconds; its text stays on
/diagnostics. A clock-jump notice or a refused pose can come with every message (in the node
the pose screen counts refused poses before they get here): each kind is logged at most every
LOG_THROTTLE_S seconds (log_throttle.LogThrottle), counted as the same when only its numbers
changed. A refused sample
(non-finite, or a repeat of an earlier one, from a resumed journal) is logged each time: each
names its sample, and there is one per sample given.
"""

import re
import time

from quatcal_ros.core import conventions
from quatcal_ros.core.units import shown
from quatcal_ros.ros.diagnostics import describe_result
from quatcal_ros.stream.log_throttle import LogThrottle, WARNING_REPEAT_S
from quatcal_ros.stream.session import EstimateUpdated, Notice, Rejected, SampleCaptured

# The numbers of a line (residuals, counts, stamps): the same line with new numbers is not new.
NUMBER = re.compile(r'[-+]?\d[\d.]*(?:e[-+]?\d+)?')
# Characters of a standing warning's repeat ('still: ...').
REPEAT_CHARACTERS = 160


class EventLog:
    """The node's log lines for the session's events (module docstring)."""

    def __init__(self, logger, clock=time.monotonic):
        self.logger = logger
        self.clock = clock                # seconds, for the throttle
        self._rejected_samples = set()   # reported already: each is logged once
        self._throttle = LogThrottle()    # per line without its numbers
        self._refusals_logged = {}        # a ~/capture refusal's key: when last logged
        self._warnings = LogThrottle(WARNING_REPEAT_S)   # per estimate warning, numbers aside
        self._standing = set()            # the keys of the last estimate's warnings

    def reset(self):
        """Forget the samples reported rejected and the throttled lines (a cleared session)."""
        self._rejected_samples = set()
        self._throttle.clear()
        self._refusals_logged.clear()
        self._warnings.clear()
        self._standing = set()

    def log(self, events, move_check, saved=None):
        """
        Log `events`; move_check(result) returns the moved-marker check's messages.

        saved: how many of the session's samples are on disk (the first ones), if known: a
        captured sample beyond them is said to wait in memory.
        """
        for event in events:
            if isinstance(event, SampleCaptured):
                self.sample(event, saved is not None and event.index >= saved)
            elif isinstance(event, EstimateUpdated):
                self._estimate(event.result, move_check(event.result))
            elif isinstance(event, Rejected):
                text = f'rejected {event.what}: {event.reason}'
                if event.what == 'sample' or self._due(text):
                    self.logger.info(text)
            elif isinstance(event, Notice) and event.code == 'time_jump':
                if self._due(event.text):
                    self.logger.info(event.text)
            elif isinstance(event, Notice):
                self.logger.info(event.text)

    def sample(self, event, unsaved=False):
        """Log the SampleCaptured `event`: index, stamp, link position; `unsaved`: not on disk."""
        position = ', '.join(f'{v:.3f}' for v in event.sample.link.position)
        waiting = ('; not yet saved: kept in memory, written with the next sample'
                   if unsaved else '')
        self.logger.info(f'sample {event.index} captured at stamp '
                         f'{event.sample.stamp_ns * 1e-9:.3f} s (link at [{position}] m{waiting})')

    def _estimate(self, result, moved):
        self.logger.info(describe_result(result))
        rejected = {entry['sample']: entry['reason'] for entry in result.rejected
                    if 'sample' in entry}
        for index in sorted(set(rejected) - self._rejected_samples):
            self.logger.info(f'rejected sample {index}: {rejected[index]}')
        self._rejected_samples = set(rejected)
        for warning, text in self._warnings_due(result.warnings):
            # ('not checked yet' is a state, said as such; rclpy wants one severity a line)
            if conventions.unchecked([warning]):
                self.logger.info(text)
            else:
                self.logger.warning(text)
        self.messages(moved)

    def _warnings_due(self, warnings):
        """
        Return (warning, text to log) of an estimate's `warnings` (module docstring).

        In full when new, shortened while it stands; either at most every WARNING_REPEAT_S
        (one that comes and goes with every estimate is not new each time).
        """
        now, due, standing = self.clock(), [], set()
        for warning in warnings:
            key = NUMBER.sub('#', warning)
            standing.add(key)
            if self._warnings.due(key, now) is None:
                continue
            due.append((warning, warning if key not in self._standing else
                        f'still: {shown(warning, REPEAT_CHARACTERS)} (in full on /diagnostics)'))
        self._standing = standing
        return due

    def capture_refused(self, reason):
        """
        Log a refused ~/capture: the same refusal (numbers aside) once per LOG_THROTTLE_S.

        A client that asks until the robot is still calls many times a second; each answer
        has its reason, the log counts the repeats.
        """
        text = f'capture refused: {reason}'
        key, now = NUMBER.sub('#', text), self.clock()
        count = self._throttle.due(key, now)
        if count is None:
            return
        if count > 1:
            text += (f' ({count - 1} more like it since it was logged '
                     f'{now - self._refusals_logged[key]:.0f} s ago)')
        self._refusals_logged[key] = now
        self.logger.info(text)

    def _due(self, text):
        """
        Return whether to log `text`, numbers aside not logged within LOG_THROTTLE_S.

        The callers log at their own line per severity: rclpy insists on one per call site.
        """
        return self._throttle.due(NUMBER.sub('#', text), self.clock()) is not None

    def messages(self, messages):
        """Log (level, text) pairs: level 'error', 'warning' or 'info'."""
        for level, text in messages:   # one call site per severity (rclpy insists)
            if level == 'error':
                self.logger.error(text)
            elif level == 'warning':
                self.logger.warning(text)
            else:
                self.logger.info(text)
