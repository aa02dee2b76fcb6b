"""
The offset of the two streams' clocks, from when their poses arrive.

A pose arrives some time after its stamp: its latency (transport, a detector's processing).
The smallest (arrival - stamp) a stream shows over a status period is its clock's offset from
the node's clock plus its shortest latency, and the difference of the two streams' is the
offset of their clocks to within their latencies (tens of milliseconds for a robot driver and
a camera's). Stamps from computers whose clocks are not synchronised show it in seconds: their
poses pair with the wrong partners (within the link buffer, 2 s), or with none, and only the
residual says something is wrong. The replay reads the same from a bag's log times
(ros.bag.clock_offset_ns).
"""

from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.stream.message_checks import LINK, SENSOR

# Clocks further apart than this are named: more than a detector's processing takes.
APART_NS = 500_000_000


class ArrivalLag:
    """The smallest (arrival - stamp) of each stream, per status period."""

    def __init__(self):
        self._period = {}   # stream: its smallest lag in the period under way
        self.lag_ns = {}    # stream: its smallest lag in the last period in which it came

    def note(self, stream, stamp_ns, arrived_ns):
        """
        Note a pose of `stream` (message_checks.LINK or SENSOR) stamped stamp_ns.

        A node clock at 0 (use_sim_time before any /clock) tells nothing: not noted.
        """
        if arrived_ns <= 0:
            return
        lag = arrived_ns - stamp_ns
        if lag < self._period.get(stream, lag + 1):
            self._period[stream] = lag

    def end_period(self):
        """Close the period: its lags are those judged from now on."""
        self.lag_ns.update(self._period)
        self._period = {}

    def offset_ns(self, configured_ns=0):
        """
        Return what to add to the sensor stamps beyond `configured_ns`, or None.

        configured_ns: the sensor time offset applied already (sensor_time_offset_s).
        """
        if LINK not in self.lag_ns or SENSOR not in self.lag_ns:
            return None
        return self.lag_ns[SENSOR] - configured_ns - self.lag_ns[LINK]


def stamps_apart(offset_ns, digits=2):
    """
    Return 'the sensor stamps run X s behind the link stamps' (or 'ahead of').

    offset_ns: what to add to the sensor stamps (positive: they run behind).
    """
    return (f'the sensor stamps run {abs(offset_ns) / NS_PER_S:.{digits}f} s '
            f'{"behind" if offset_ns > 0 else "ahead of"} the link stamps')


def problem(offset_ns, configured_ns=0):
    """Return the warning on an offset of ArrivalLag.offset_ns, or None within APART_NS."""
    if offset_ns is None or abs(offset_ns) <= APART_NS:
        return None
    given = (f' (with sensor_time_offset_s {configured_ns / NS_PER_S:g})'
             if configured_ns else '')
    late = 'sensor' if offset_ns > 0 else 'link'   # the stream whose poses come later
    return (f'{stamps_apart(offset_ns)}{given}, against the times their poses arrive: the two '
            'clocks are not synchronised (synchronise them, e.g. with chrony, or set '
            f'sensor_time_offset_s:={(configured_ns + offset_ns) / NS_PER_S:.2f}, then call '
            f'~/reset: samples taken keep their pairing), or the {late} poses take that long '
            'to arrive')
