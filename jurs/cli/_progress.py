"""What the command line says on stderr while a run is under way: a fit's steps
(``ProgressBar``) and the stages that are one long call with no steps to count, such as an
adaptive fit's solve or a fine mesh (``StageClock``). Short runs print nothing; a
terminal gets a line redrawn in place, a pipe or a log a few plain lines."""

from __future__ import annotations

import sys
import threading
import time


class ProgressBar:
    """Progress of a fit on stderr, shown only once a run has taken over ``delay`` seconds
    (short fits print nothing). On a terminal, one line redrawn in place (``\\r``); on
    anything else (a pipe, a log file) a few plain lines: one when first shown, one as each
    quarter of the steps is passed, and one at the end where that was not yet said, so a
    log gets a handful of lines, not a frame a step. ``tty`` None asks the stream
    (``isatty()``)."""

    #: Plain lines (not a terminal): one as each of these fractions of the steps is passed.
    PLAIN_STEPS = 4

    def __init__(
        self,
        label: str,
        delay: float = 1.0,
        width: int = 30,
        stream=None,
        enabled: bool = True,
        tty: bool | None = None,
    ):
        self.label, self.delay, self.width = label, delay, width
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.tty = is_terminal(self.stream) if tty is None else bool(tty)
        self.start = time.perf_counter()
        self.drawn = False
        self.last: tuple[int, int] | None = None  # the latest (done, total)
        self.said: tuple[int, int] | None = None  # the latest plain line's (done, total)
        self.quarter = -1  # the latest quarter a plain line was written for

    def __call__(self, done: int, total: int) -> None:
        self.last = (done, total)
        elapsed = time.perf_counter() - self.start
        if not self.enabled or (elapsed < self.delay and not self.drawn):
            return
        frac = done / total if total else 1.0
        if not self.tty:
            quarter = int(frac * self.PLAIN_STEPS)
            if quarter > self.quarter:
                self._line(done, total, elapsed)
                self.quarter = quarter
            self.drawn = True
            return
        bar = "#" * int(round(frac * self.width))
        self.stream.write(
            f"\r{self.label} [{bar:<{self.width}}] {done}/{total} steps {elapsed:5.1f} s"
        )
        self.stream.flush()
        self.drawn = True

    def _line(self, done: int, total: int, elapsed: float) -> None:
        percent = 100 * done / total if total else 100.0
        self.stream.write(f"{self.label}: {done}/{total} steps ({percent:.0f} %) {elapsed:.1f} s\n")
        self.stream.flush()
        self.said = (done, total)

    def close(self) -> None:
        """End the bar's line (once), so that what follows starts a line of its own; in
        plain lines, say where the run stopped if the last line did not."""
        if not self.drawn:
            return
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
        elif self.last is not None and self.last != self.said:
            self._line(*self.last, time.perf_counter() - self.start)
        self.drawn = False


def is_terminal(stream) -> bool:
    """Whether ``stream`` is a terminal (a closed or odd stream counts as not)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class StageClock:
    """A stage of a run that is one call with no steps to count (an adaptive fit's solve,
    marching a fine lattice), said on stderr while it lasts: nothing if it ends within
    ``delay`` seconds; else a line when ``delay`` has passed and again each time the
    elapsed time doubles (a handful of lines however long it runs), then one saying how
    long it took. The lines come from a timer thread, so the call being timed is not
    touched; the thread waits on an event and ends with the stage.

    Use as a context manager: ``with StageClock("bunny.ply: meshing"): ...``."""

    def __init__(self, label: str, delay: float = 5.0, stream=None, enabled: bool = True):
        self.label, self.delay = label, float(delay)
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.lines = 0  # the lines written while the stage ran
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._start = 0.0

    def __enter__(self) -> StageClock:
        self._start = time.perf_counter()
        if self.enabled:
            self._thread = threading.Thread(target=self._tick, daemon=True)
            self._thread.start()
        return self

    def _tick(self) -> None:
        wait = self.delay
        while not self._stop.wait(wait):
            elapsed = time.perf_counter() - self._start
            self._write(f"{self.label}: {elapsed:.0f} s so far")
            # The next line when the elapsed time has doubled (a tenth of a second at
            # the least, so that a zero delay does not spin).
            wait = max(elapsed, self.delay, 0.1)

    def _write(self, line: str) -> None:
        try:
            self.stream.write(line + "\n")
            self.stream.flush()
        except (ValueError, OSError):  # a closed stream: the run goes on unsaid
            return
        self.lines += 1

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.lines and exc[0] is None:
            self._write(f"{self.label}: done in {time.perf_counter() - self._start:.1f} s")
