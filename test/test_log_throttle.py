"""The log throttle (one line per kind of event every 5 s) and the node's event log over it."""

from quatcal_ros.ros.event_log import EventLog
from quatcal_ros.stream.log_throttle import LOG_THROTTLE_S, LogThrottle, REMEMBERED_KINDS
from quatcal_ros.stream.session import Notice, Rejected


class Lines:
    """A logger that keeps its lines as (severity, text)."""

    def __init__(self):
        self.lines = []

    def info(self, text):
        self.lines.append(('info', text))

    def warning(self, text):
        self.lines.append(('warning', text))


def test_each_key_is_due_at_once_then_every_period_with_the_count_held_back():
    throttle = LogThrottle(period=5.0)
    assert throttle.due('a', 0.0) == 1
    assert [throttle.due('a', 0.1 * k) for k in range(1, 10)] == [None] * 9
    assert throttle.due('b', 1.0) == 1            # another key: its own period
    assert throttle.due('a', 5.0) == 10           # the nine held back and this one
    assert throttle.due('a', 9.9) is None
    throttle.clear()
    assert throttle.due('a', 10.0) == 1           # cleared: due again at once


def test_keys_whose_period_passed_are_forgotten_beyond_the_bound():
    throttle = LogThrottle(period=1.0)
    for k in range(REMEMBERED_KINDS):
        assert throttle.due(f'old {k}', 0.0) == 1
    assert throttle.due('old 7', 0.2) is None      # held back: its count must not be lost
    assert throttle.due('fresh', 0.5) == 1        # the old ones still within their period
    assert len(throttle._due) == REMEMBERED_KINDS + 1
    assert throttle.due('newer', 2.0) == 1        # their period passed: forgotten
    assert set(throttle._due) == {'newer', 'old 7'}
    assert throttle.due('old 3', 2.1) == 1
    assert throttle.due('old 7', 2.2) == 2        # the one held back, and this one


def test_event_log_throttles_refusals_per_kind_not_per_line_of_code():
    """Two kinds within 5 s both reach the log; the same kind with new numbers not."""
    now = [100.0]
    logger = Lines()
    log = EventLog(logger, clock=lambda: now[0])
    order = Rejected('link_pose', 'stamp 1.000 s is older than the previous one (2.000 s)')
    log.log([order, Notice('the clock jumped back by 3.0 s', 'time_jump'),
             Rejected('link_pose', 'stamp 1.500 s is older than the previous one (2.500 s)'),
             Notice('the clock jumped back by 4.0 s', 'time_jump')], lambda result: None)
    assert logger.lines == [
        ('info', f'rejected link_pose: {order.reason}'),
        ('info', 'the clock jumped back by 3.0 s')]
    now[0] += LOG_THROTTLE_S
    log.log([Rejected('link_pose', 'stamp 7.000 s is older than the previous one (8.000 s)')],
            lambda result: None)
    assert logger.lines[-1] == ('info', 'rejected link_pose: stamp 7.000 s is older than the '
                                'previous one (8.000 s)')


def test_every_refused_sample_is_logged_each_naming_its_own():
    logger = Lines()
    log = EventLog(logger, clock=lambda: 0.0)
    log.log([Rejected('sample', f'sample {k} of those given repeats sample {k + 3} exactly')
             for k in range(4)], lambda result: None)
    assert [text for _, text in logger.lines] == [
        f'rejected sample: sample {k} of those given repeats sample {k + 3} exactly'
        for k in range(4)]


def test_event_log_reset_logs_every_kind_again():
    now = [0.0]
    logger = Lines()
    log = EventLog(logger, clock=lambda: now[0])
    event = Notice('the clock jumped back by 3.0 s', 'time_jump')
    log.log([event, event], lambda result: None)
    assert len(logger.lines) == 1
    log.reset()                                   # a cleared session: its first lines again
    log.log([event], lambda result: None)
    assert len(logger.lines) == 2


def test_a_standing_problem_is_logged_once_after_its_delay_and_again_when_it_returns():
    from quatcal_ros.stream.log_throttle import StandingLog
    log = StandingLog(after=5, key=lambda text: text.split(' (')[0])
    assert log.due(['no frame tool_0 (seen: a)'], 0) == []          # not yet 5 long
    assert log.due(['no frame tool_0 (seen: a, b)'], 5) == ['no frame tool_0 (seen: a, b)']
    assert log.due(['no frame tool_0 (seen: a, b, c)'], 9) == []    # said, still standing
    assert log.due([], 10) == []                                     # gone...
    assert log.due(['no frame tool_0 (seen: a)'], 11) == []          # ... back: 5 again
    assert log.due(['no frame tool_0 (seen: a)'], 16) == ['no frame tool_0 (seen: a)']
    once = StandingLog(forget=False)
    assert once.due(['x'], 0) == ['x'] and once.due([], 1) == [] and once.due(['x'], 2) == []


def test_a_capture_refused_again_and_again_is_logged_once_per_period_with_its_count():
    # A client polling ~/capture until the robot is still flooded the log: a line per call.
    now = [0.0]
    logger = Lines()
    log = EventLog(logger, clock=lambda: now[0])
    for k in range(10):
        now[0] = 0.2 * k
        log.capture_refused(f'robot is moving: link rotated {k + 1}.0 deg in the last 1.0 s')
    log.capture_refused('no motion since the last sample (0.1 deg, 0.2 mm): move the robot first')
    assert logger.lines == [
        ('info', 'capture refused: robot is moving: link rotated 1.0 deg in the last 1.0 s'),
        ('info', 'capture refused: no motion since the last sample (0.1 deg, 0.2 mm): move the '
                 'robot first')]   # another refusal: at once
    now[0] = 600.0   # asked again ten minutes later
    log.capture_refused('robot is moving: link rotated 0.5 deg in the last 1.0 s')
    assert logger.lines[-1] == ('info', 'capture refused: robot is moving: link rotated 0.5 deg '
                                'in the last 1.0 s (9 more like it since it was logged 600 s '
                                'ago)')
    log.reset()
    log.capture_refused('robot is moving: link rotated 0.5 deg in the last 1.0 s')
    assert logger.lines[-1] == ('info', 'capture refused: robot is moving: link rotated 0.5 deg '
                                'in the last 1.0 s')


def test_a_warning_every_estimate_repeats_is_logged_in_full_once_then_shortened_rarely():
    # A 900-character frame-convention warning came back in full every 5 s of estimates.
    from quatcal_ros.stream.log_throttle import WARNING_REPEAT_S
    now = [0.0]
    log = EventLog(Lines(), clock=lambda: now[0])
    long = 'frame convention: another one fits far better ' + 'and says so at length ' * 40
    residual = 'high residual {:.2f} deg RMS'

    def estimate(*warnings):   # the texts an estimate with these warnings logs
        return [text for _, text in log._warnings_due(list(warnings))]
    assert estimate(long, residual.format(1.5)) == [long, 'high residual 1.50 deg RMS']
    for k in range(1, 12):   # an estimate every 5 s for 55 s, the same warnings: nothing
        now[0] = 5.0 * k
        assert estimate(long, residual.format(1.5 + 0.1 * k)) == []
    now[0] = WARNING_REPEAT_S   # still standing after a minute: shortened
    assert estimate(long) == [f'still: {long[:157]}... (in full on /diagnostics)']
    assert estimate(long) == []
    # The residual went away with that estimate: back, it is new again, in full; one that
    # comes and goes with every estimate is not logged each time.
    now[0] += 10.0
    assert estimate(long, residual.format(2.0)) == ['high residual 2.00 deg RMS']
    now[0] += 1.0
    assert estimate(long) == [] and estimate(long, residual.format(2.1)) == []
    log.reset()   # a cleared session: in full again
    assert estimate(long) == [long]
