"""
Log lines kept few: LogThrottle per kind of event, StandingLog per standing problem.

LogThrottle logs one line per kind of event at most every LOG_THROTTLE_S.

rclpy's own throttle (throttle_duration_sec) is per line of code: of several kinds of event
logged from one line (a bad message's reasons, a refused view's, an estimate's warnings), only
the first would get through. LogThrottle keeps one time per key instead, and counts the events
it held back, so that the next line can say how many there were.
"""

from collections import Counter

# Each kind of event is logged at most once per this many seconds (steady clock).
LOG_THROTTLE_S = 5.0
# A warning that every estimate repeats is logged in full when it comes, then shortened at
# most once per this many seconds while it stands (it is on /diagnostics all along).
WARNING_REPEAT_S = 60.0
# Kinds remembered before a new one makes those whose period has passed, with nothing held
# back, be forgotten (their next line is due at once anyway): a soft bound on memory when keys
# carry free text, such as warnings (kinds still within their period stay).
REMEMBERED_KINDS = 100


class LogThrottle:
    """
    At most one log line per key every `period`; `due(key, now)` decides.

    `period` and `now` are in one unit of the caller's steady clock (seconds, or
    nanoseconds).
    """

    def __init__(self, period=LOG_THROTTLE_S):
        self.period = period
        self._due = {}              # key: when its next line may be logged
        self._held = Counter()      # key: events since its last line, held back

    def due(self, key, now):
        """
        Note an event of `key`; return how many to report if a line is due, else None.

        The first event of a key is due at once, later ones at most every `period`: the
        number returned counts the events since the key's previous line, this one included.
        """
        self._held[key] += 1
        due = self._due.get(key)
        if due is not None and now < due:
            return None
        if due is None and len(self._due) >= REMEMBERED_KINDS:
            self._forget(now)
        self._due[key] = now + self.period
        count, self._held[key] = self._held[key], 0
        return count

    def clear(self):
        """Forget every key: each is due again at its next event."""
        self._due.clear()
        self._held.clear()

    def _forget(self, now):
        for key in [key for key, due in self._due.items() if due <= now and not self._held[key]]:
            del self._due[key]
            self._held.pop(key, None)


class StandingLog:
    """
    Which of the problems a status finds to log: each once while it stands.

    A problem is known by key(text) (its text, by default: a text that carries a changing
    number needs a key without it). It is logged once it has stood for `after` (the caller's
    steady clock; 0: at once), then not again while it stands; with `forget`, one that went
    away and comes back is logged again.
    """

    def __init__(self, after=0, key=None, forget=True):
        self.after = after
        self.key = key or (lambda text: text)
        self.forget = forget
        self._since = {}    # key: when it was first seen standing
        self._said = set()  # keys logged

    def due(self, texts, now):
        """Return those of the problems standing now, `texts`, to log now."""
        standing, due = {}, []
        for text in texts:
            key = self.key(text)
            standing[key] = since = self._since.get(key, now)
            if now - since >= self.after and key not in self._said:
                self._said.add(key)
                due.append(text)
        self._since = standing
        if self.forget:
            self._said &= set(standing)
        return due
