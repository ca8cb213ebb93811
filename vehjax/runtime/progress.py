"""One progress bar for the long loops of the package: a study's chunks (:func:`vehjax.run`) and a
fit's iterations (:func:`vehjax.tune.fit`).

tqdm's bar (``tqdm.auto``: a widget in Jupyter, text on stderr elsewhere) when tqdm is
installed, else one text line on stderr rewritten in place (``"\\r"``) and ended by a newline
when the loop is done. The caller decides whether it shows (``enabled``) and says what each
update shows: the tqdm postfix and the text line's own words; the elapsed seconds are appended
to the text line here.

::

    bar = Progress(total=10, label="vehjax.tune (UKF)", enabled=True)
    for i in range(1, 11):
        bar.update(i, postfix=f"loss={f:.6g}", text=f"iteration {i}/10, loss {f:.6g}")
    bar.close()

Limits: one bar at a time per loop; the text line assumes a terminal that honours ``"\\r"``.
"""

from __future__ import annotations

import sys
import time

__all__ = ["Progress", "text_bar"]


def text_bar(done: int, total: int, width: int = 30) -> str:
    """``"###....."``: ``width`` characters, the share ``done / total`` of them filled."""
    filled = round(width * done / max(total, 1))
    return "#" * filled + "." * (width - filled)


class Progress:
    """A bar over ``total`` units of work.

    Args:
        total: the number of units (chunks, iterations) the loop may take.
        label: the bar's description (tqdm's ``desc``).
        enabled: False makes every method a no-op (nothing is written).
        unit, bar_format, postfix: tqdm's arguments of those names (the initial postfix
            string), used only with tqdm.
        interval: the text line is rewritten at most once per ``interval`` seconds, except
            for the last unit (tqdm throttles itself).
        first_text: the text line written at once when tqdm is missing (None: nothing until
            the first update).
    """

    def __init__(self, total: int, label: str, enabled: bool, *, unit: str = "it",
                 bar_format: str | None = None, postfix: str | None = None,
                 interval: float = 0.0, first_text: str | None = None):
        self.total, self.label, self.enabled, self.interval = total, label, enabled, interval
        self.bar, self.closed = None, False
        self.t0 = self.last = time.perf_counter()
        self.text = ""
        if not enabled:
            return
        try:
            from tqdm.auto import tqdm
        except ImportError:  # the text line
            if first_text is not None:
                self._write(first_text, 0)
            return
        self.bar = tqdm(total=total, desc=label, unit=unit, file=sys.stderr,
                        bar_format=bar_format, postfix=postfix)

    @property
    def elapsed(self) -> float:
        """Seconds since the bar was made."""
        return time.perf_counter() - self.t0

    def update(self, done: int, postfix: str, text: str) -> None:
        """``done`` units are done: tqdm's bar moves there with ``postfix``; the text line
        becomes ``"{text}, {elapsed:.1f} s"``. Reaching ``total`` closes the bar."""
        if not self.enabled or self.closed:
            return
        if self.bar is not None:
            self.bar.set_postfix_str(postfix, refresh=False)
            self.bar.update(done - self.bar.n)
            if done >= self.total:
                self.close()
            return
        now = time.perf_counter()
        self.text = text
        if now - self.last < self.interval and done < self.total:
            return
        self._write(text, done)

    def close(self) -> None:
        """The loop ended (perhaps before ``total``): the bar is closed, the text line
        rewritten with its latest words and ended. Idempotent."""
        if not self.enabled or self.closed:
            return
        self.closed = True
        if self.bar is not None:
            self.bar.close()
            return
        self._end()

    def _write(self, text: str, done: int) -> None:
        self.last = time.perf_counter()
        self.text = text
        sys.stderr.write(f"\r{text}, {self.last - self.t0:.1f} s")
        if done >= self.total:
            self.closed = True
            sys.stderr.write("\n")
        sys.stderr.flush()

    def _end(self) -> None:
        sys.stderr.write(f"\r{self.text}, {time.perf_counter() - self.t0:.1f} s\n")
        sys.stderr.flush()
