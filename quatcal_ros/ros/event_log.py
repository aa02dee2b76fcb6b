"""
What the live node says in its log about the session: samples, estimates, refusals, files.

`EventLog.log(events, move_check)` writes one line per session event (stream/session.py):
a captured sample with its link position, each estimate (diagnostics.describe_result) with
the samples newly rejected since the last one and its warnings, throttled refusals and
notices, and the moved-marker warning that `move_check(result)` returns. `messages` writes
the (level, text) pairs of the journal and the result files.

An estimate's warnings come back with every estimate: each is logged at most every
LOG_THROTTLE_S seconds, counted as the same warning when only its numbers changed (rclpy's own
throttle is per line of code: it would let only the first of several warnings through).
"""

import re
import time

from quatcal_ros.ros.diagnostics import describe_result
from quatcal_ros.stream.message_checks import LOG_THROTTLE_S
from quatcal_ros.stream.session import EstimateUpdated, Notice, Rejected, SampleCaptured

# The numbers of a warning (residuals, counts): the same warning with new numbers is not new.
NUMBER = re.compile(r'[-+]?\d[\d.]*(?:e[-+]?\d+)?')


class EventLog:
    """The node's log lines for the session's events (module docstring)."""

    def __init__(self, logger, clock=time.monotonic):
        self.logger = logger
        self.clock = clock                # seconds, for the warnings' throttle
        self._rejected_samples = set()   # reported already: each is logged once
        self._warned = {}                 # warning without its numbers -> when last logged

    def reset(self):
        """Forget the samples reported rejected (the session was cleared)."""
        self._rejected_samples = set()

    def log(self, events, move_check):
        """Log `events`; move_check(result) returns a moved-marker warning or None."""
        for event in events:
            if isinstance(event, SampleCaptured):
                self.sample(event)
            elif isinstance(event, EstimateUpdated):
                self._estimate(event.result, move_check(event.result))
            elif isinstance(event, Rejected):
                self.logger.info(f'rejected {event.what}: {event.reason}',
                                 throttle_duration_sec=LOG_THROTTLE_S)
            elif isinstance(event, Notice) and event.code == 'time_jump':
                self.logger.info(event.text, throttle_duration_sec=LOG_THROTTLE_S)
            elif isinstance(event, Notice):
                self.logger.info(event.text)

    def sample(self, event):
        """Log the SampleCaptured `event`: index, stamp and link position."""
        position = ', '.join(f'{v:.3f}' for v in event.sample.link.position)
        self.logger.info(f'sample {event.index} captured at stamp '
                         f'{event.sample.stamp_ns * 1e-9:.3f} s (link at [{position}] m)')

    def _estimate(self, result, moved):
        self.logger.info(describe_result(result))
        rejected = {entry['sample']: entry['reason'] for entry in result.rejected
                    if 'sample' in entry}
        for index in sorted(set(rejected) - self._rejected_samples):
            self.logger.info(f'rejected sample {index}: {rejected[index]}')
        self._rejected_samples = set(rejected)
        for warning in result.warnings:
            self._throttled_warning(warning)
        if moved:
            self.logger.warning(moved)

    def _throttled_warning(self, text):
        """Log `text` unless the same warning, numbers aside, was logged within LOG_THROTTLE_S."""
        now = self.clock()
        kind = NUMBER.sub('#', text)
        last = self._warned.get(kind)
        if last is not None and now - last < LOG_THROTTLE_S:
            return
        if len(self._warned) > 100:   # forget the warnings that are no longer throttled
            self._warned = {k: t for k, t in self._warned.items() if now - t < LOG_THROTTLE_S}
        self._warned[kind] = now
        self.logger.warning(text)

    def messages(self, messages):
        """Log (level, text) pairs: level 'error', 'warning' or 'info'."""
        for level, text in messages:   # one call site per severity (rclpy insists)
            if level == 'error':
                self.logger.error(text)
            elif level == 'warning':
                self.logger.warning(text)
            else:
                self.logger.info(text)
