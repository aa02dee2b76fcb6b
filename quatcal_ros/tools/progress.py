"""
A one-line progress display for long runs, on a terminal only.

Redrawn in place (carriage return) at most every `interval_s` seconds, so callers may call
`update` as often as they like; silent when the stream is not a terminal or when disabled.
"""

import sys
import time


class Progress:
    """`label: done/total (pct)  extra  [elapsed, ~left]` on stderr while something runs."""

    def __init__(self, total, label='', stream=None, enabled=True, interval_s=0.1):
        self.stream = sys.stderr if stream is None else stream
        self.total = total
        self.label = label
        self.interval_s = interval_s
        is_tty = getattr(self.stream, 'isatty', None)
        self.enabled = bool(enabled and is_tty and is_tty())
        self._start = time.monotonic()
        self._next = self._start
        self._width = 0

    def update(self, done, extra=''):
        """Show `done` of `total`, and `extra` (a str or a function returning one)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.interval_s
        self._draw(done, extra() if callable(extra) else extra, now)

    def close(self, done=None, extra=''):
        """Draw the final state (when `done` is given) and end the line, if one was drawn."""
        if not self.enabled:
            return
        if done is not None:
            self._draw(done, extra() if callable(extra) else extra, time.monotonic())
        if self._width:
            self.stream.write('\n')
            self.stream.flush()
        self.enabled = False

    def _draw(self, done, extra, now):
        elapsed = now - self._start
        text = f'{self.label}: {done}/{self.total}'
        if self.total:
            fraction = min(done / self.total, 1.0)
            text += f' ({100 * fraction:.0f} %)'
        if extra:
            text += f'  {extra}'
        text += f'  [{elapsed:.1f} s'
        if self.total and 0 < done < self.total:
            text += f', ~{elapsed * (self.total - done) / done:.0f} s left'
        text += ']'
        pad = max(self._width - len(text), 0)
        self._width = len(text)
        self.stream.write('\r' + text + ' ' * pad)
        self.stream.flush()
