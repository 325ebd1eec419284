"""Progress of a long stage, for people (a bar on a terminal) and for CI (plain lines in a log).

Stages keep their plain ``progress: Callable[[int], None]`` callback, called with the units each step
finished (inputs, samples, logs, ...), and announce the total once they know it with ``report_total``;
a plain callable (a test's ``list.append``) simply ignores the total. ``ProgressReporter`` is the
callback the CLI hands them:

* ``mode="bar"`` (stderr is a terminal): a rich bar with done/total, percentage, rate and ETA, redrawn at
  most ten times a second from the caller's thread (no refresh thread, so worker pools may still fork);
* ``mode="lines"`` (a CI log, a pipe): a time heartbeat, one line every ``interval_s`` seconds (default 5,
  environment variable ``LOGPIPE_PROGRESS_INTERVAL``) led by the time it has run, e.g. ``predict: 0:00:05
  1,200/5,000 samples (24%) 310/s ETA 0:00:12``, plus a final line (none when there was nothing to do); no line
  when the total is announced, so a run shorter than the interval writes only its final line; lines go to stderr
  only, never wrapped, since stdout carries ``--json``. A heartbeat thread writes the line when it is due even
  while the stage is inside one long batch (a network's forward pass, a worker's shard), so the gaps are the
  interval whatever the batch size; it writes only under the reporter's lock, which a fork waits for
  (``os.register_at_fork``), so worker pools may still fork;
* ``mode="off"``: nothing (``-q``).

Times are seconds of a monotonic clock (injectable for tests). This module imports only the standard
library at import time: stages and their pool workers import it, rich is loaded for the bar alone.
"""

from __future__ import annotations

import datetime
import os
import sys
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable
from types import TracebackType
from typing import TYPE_CHECKING, Literal, Protocol, TextIO, runtime_checkable

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import Progress, TaskID

Mode = Literal["bar", "lines", "off"]

INTERVAL_ENV = "LOGPIPE_PROGRESS_INTERVAL"
DEFAULT_INTERVAL_S = 5.0
RATE_WINDOW_S = 30.0
"""The rate (and so the ETA) is measured over about the last 30 s: a resumed run's instantly skipped
shards, or a slow start-up, stop counting once they are that far behind."""
_BAR_REFRESH_S = 0.1
HEARTBEAT_THREAD = "logpipe-progress-heartbeat"
"""Name of the heartbeat threads; ``logpipe.executor`` forks past them (they hold no lock across a fork)."""
_LIVE: weakref.WeakSet[ProgressReporter] = weakref.WeakSet()


def _before_fork() -> None:
    for reporter in list(_LIVE):
        reporter._lock.acquire()  # no heartbeat is half-way through a line (and stderr's lock) in the child


def _after_fork() -> None:
    for reporter in list(_LIVE):
        if reporter._lock.locked():
            reporter._lock.release()


os.register_at_fork(before=_before_fork, after_in_parent=_after_fork, after_in_child=_after_fork)


@runtime_checkable
class TotalAware(Protocol):
    """A progress callback (called with the number of units just finished) that also takes the total."""

    def __call__(self, done: int, /) -> None: ...

    def total(self, units: int) -> None: ...


def report_total(progress: Callable[[int], None] | None, units: int) -> None:
    """Tell ``progress`` how many units the stage will report in all, when it wants to know."""
    if isinstance(progress, TotalAware):
        progress.total(units)


def interval_from_env(default: float = DEFAULT_INTERVAL_S) -> float:
    """Seconds between plain progress lines: ``LOGPIPE_PROGRESS_INTERVAL`` when it is a number >= 0."""
    raw = os.environ.get(INTERVAL_ENV, "")
    try:
        value = float(raw)
    except ValueError:
        return default  # unset or malformed: a typo must not stop a long run
    return value if value >= 0 else default


def format_duration(seconds: float) -> str:
    """``H:MM:SS`` (whole seconds, rounded up so an ETA never reads 0 while work remains)."""
    return str(datetime.timedelta(seconds=max(0, int(-(-seconds // 1)))))


def format_rate(per_second: float) -> str:
    """Units per second with the digits that matter: ``310``, ``4.2``, ``0.37``."""
    if per_second >= 100:
        return f"{per_second:,.0f}"
    if per_second >= 1:
        return f"{per_second:.1f}"
    return f"{per_second:.2f}"


class ProgressReporter:
    """Counts finished units against a total and shows it (see the module docstring).

    Args:
        label: the stage, first word of every line (``predict``).
        unit: what is counted, plural (``samples``).
        mode: ``bar``, ``lines`` or ``off``.
        interval_s: seconds between plain lines (default: ``interval_from_env()``); 0 prints one per call.
        stream: where plain lines go (default: ``sys.stderr`` at the time of writing).
        console: the rich console of the bar (default: a new one on stderr).
        clock: monotonic seconds (tests inject a fake one).
        heartbeat: in lines mode, write the due line from a thread even when no unit finishes (default: on with
            the real clock and an interval above 0).
    """

    def __init__(self, label: str, unit: str, mode: Mode, *, interval_s: float | None = None,
                 stream: TextIO | None = None, console: Console | None = None,
                 clock: Callable[[], float] = time.monotonic, heartbeat: bool | None = None) -> None:
        self.label = label
        self.unit = unit
        self.mode: Mode = mode
        self.interval_s = interval_from_env() if interval_s is None else interval_s
        self.done = 0
        self.expected: int | None = None
        self._stream = stream
        self._console = console
        self._clock = clock
        self._started = clock()
        self._last_line = self._started
        self._last_refresh = -float("inf")
        # (time, done) samples for the rate; the first is at or before the start of the rate window.
        self._samples: deque[tuple[float, int]] = deque([(self._started, 0)])
        self._bar: Progress | None = None
        self._task: TaskID | None = None
        self._closed = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if heartbeat is None:
            heartbeat = clock is time.monotonic and self.interval_s > 0
        if mode == "lines" and heartbeat:
            _LIVE.add(self)
            self._thread = threading.Thread(target=self._beat, name=HEARTBEAT_THREAD, daemon=True)
            self._thread.start()

    def _beat(self) -> None:
        """The heartbeat: sleep until the next line is due, write it if nothing else did meanwhile."""
        while not self._stop.wait(max(0.05, self._last_line + self.interval_s - self._clock())):
            with self._lock:
                now = self._clock()
                if not self._closed and now - self._last_line >= self.interval_s:
                    self._last_line = now
                    self._write(self.line())

    # -- the callback the stages see ---------------------------------------------------------------------

    def __call__(self, done: int, /) -> None:
        self.advance(done)

    def total(self, units: int) -> None:
        """The number of units the stage reports in all (known once its inputs are listed)."""
        self.expected = units
        if self.done == 0:
            # The work starts now: the listing and set-up before it would make the first rates too low.
            now = self._clock()
            self._samples = deque([(now, 0)])
            self._last_line = now
        if self.mode == "bar":  # lines mode waits for the heartbeat: a "0/N" line at every start says nothing
            self._show_bar(force=True)

    def advance(self, units: int = 1) -> None:
        """``units`` more are finished."""
        self.done += units
        now = self._clock()
        if now - self._samples[-1][0] >= 1.0:
            self._samples.append((now, self.done))
        while len(self._samples) >= 2 and self._samples[1][0] <= now - RATE_WINDOW_S:
            self._samples.popleft()
        if self.mode == "lines" and now - self._last_line >= self.interval_s:
            with self._lock:
                self._last_line = now
                self._write(self.line())
        elif self.mode == "bar":
            self._show_bar(force=self.done == self.expected)

    # -- figures and lines -------------------------------------------------------------------------------

    def rate(self) -> float | None:
        """Units per second over about the last ``RATE_WINDOW_S`` seconds; None before any time has passed."""
        t0, done0 = self._samples[0]
        elapsed = self._clock() - t0
        return (self.done - done0) / elapsed if elapsed > 0 else None

    def eta(self) -> float | None:
        """Seconds left at the current rate; None when the total or the rate is unknown."""
        rate = self.rate()
        if self.expected is None or not rate:
            return None
        return max(0, self.expected - self.done) / rate

    def line(self) -> str:
        """The current state as one line, led by the time it has run: ``predict: 0:00:05 1,200/5,000 samples
        (24%) 310/s ETA 0:00:12``; before the total and the first unit, ``score: running 0:00:10``."""
        elapsed = format_duration(self._clock() - self._started)
        if self.expected is None and not self.done:
            return f"{self.label}: running {elapsed}"
        parts = [f"{self.label}: {elapsed} {self._count()}"]
        rate = self.rate()
        if rate is not None and self.done:
            parts.append(f"{format_rate(rate)}/s")
        eta = self.eta()
        if eta is not None:
            parts.append(f"ETA {format_duration(eta)}")
        return " ".join(parts)

    def final_line(self, failed: bool = False) -> str:
        """The last line: the count, the mean rate since the start, and the time it took."""
        elapsed = self._clock() - self._started
        rate = f" {format_rate(self.done / elapsed)}/s" if elapsed > 0 and self.done else ""
        how = "stopped after" if failed else "done in"
        return f"{self.label}: {self._count()}{rate} {how} {format_duration(elapsed)}"

    def _count(self) -> str:
        if self.expected is None:
            return f"{self.done:,} {self.unit}"
        text = f"{self.done:,}/{self.expected:,} {self.unit}"
        if self.expected > 0:
            text += f" ({min(100, 100 * self.done // self.expected)}%)"
        return text

    def _write(self, text: str) -> None:
        stream = self._stream or sys.stderr
        stream.write(text + "\n")
        stream.flush()  # a CI log shows the line now, not when a buffer fills

    # -- the bar -----------------------------------------------------------------------------------------

    def _show_bar(self, force: bool) -> None:
        now = self._clock()
        if not force and now - self._last_refresh < _BAR_REFRESH_S:
            return
        self._last_refresh = now
        if self._bar is None:
            self._bar, self._task = _make_bar(self.label, self.unit, self.expected, self._console)
            self._bar.start()
        assert self._task is not None
        self._bar.update(self._task, completed=self.done, total=self.expected)
        self._bar.refresh()

    # -- lifetime ----------------------------------------------------------------------------------------

    def close(self, failed: bool = False) -> None:
        """End the display: the bar disappears; in lines mode the final line is written (if anything ran)."""
        if self._closed:
            return
        with self._lock:
            self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            _LIVE.discard(self)
        if self._bar is not None:
            self._bar.stop()
        if self.mode == "lines" and (self.done or self.expected):  # nothing to do: nothing to say
            self._write(self.final_line(failed))

    def __enter__(self) -> ProgressReporter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close(failed=exc_type is not None)


def _make_bar(label: str, unit: str, total: int | None, console: Console | None) -> tuple[Progress, TaskID]:
    """A transient rich bar: label, bar, done/total unit, percentage, rate, ETA."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        Task,
        TaskProgressColumn,
        TextColumn,
        TimeRemainingColumn,
    )
    from rich.text import Text

    class RateColumn(ProgressColumn):
        def render(self, task: Task) -> Text:
            speed = task.finished_speed or task.speed
            return Text(f"{format_rate(speed)}/s" if speed else "", style="progress.data.speed")

    bar = Progress(
        TextColumn(label), BarColumn(), MofNCompleteColumn(), TextColumn(unit), TaskProgressColumn(),
        RateColumn(), TextColumn("ETA"), TimeRemainingColumn(),
        # Redrawn by ``ProgressReporter`` instead of rich's refresh thread: with no thread running, a stage's
        # worker pool can fork from this process (see ``logpipe.executor``).
        console=console or Console(stderr=True), transient=True, auto_refresh=False,
    )
    return bar, bar.add_task(label, total=total)
