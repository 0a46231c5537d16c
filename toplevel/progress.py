"""Progress of the command-line tools' long loops: click's bar on a terminal, timed lines anywhere else.

click's progress bar prints only its label when its stream is not a terminal, so a run logged to a file, piped or
run under CI shows nothing until it ends. ``progressbar`` keeps click's bar for a terminal and otherwise writes
one plain line every ``PROGRESS_LINE_INTERVAL_S`` seconds and one when the loop ends:

    simulating 3 scene(s): 40/120 (33 %), 12 s, about 24 s left
    simulating 3 scene(s): 120/120 done in 36 s

Both take the part of click's ``ProgressBar`` interface the tools use: a context manager, iteration, ``update``,
``pos`` and a settable ``length``. Progress goes to stderr unless ``file`` says otherwise: it is not a result.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import IO, Any

import click

PROGRESS_LINE_INTERVAL_S = 10.0  # seconds between two progress lines when the stream is not a terminal


def _is_terminal(stream: IO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def progressbar(
    iterable: Iterable | None = None,
    *,
    length: int | None = None,
    label: str,
    show_pos: bool = True,
    item_show_func: Callable[[Any], str | None] | None = None,
    file: IO | None = None,
    interval_s: float = PROGRESS_LINE_INTERVAL_S,
    clock: Callable[[], float] = time.monotonic,
):
    """click's progress bar on a terminal, ``LineProgress`` elsewhere (same arguments as ``click.progressbar``)."""
    stream = sys.stderr if file is None else file
    if _is_terminal(stream):
        return click.progressbar(iterable, length=length, label=label, show_pos=show_pos,
                                 item_show_func=item_show_func, file=stream)  # fmt: skip
    return LineProgress(iterable, length=length, label=label, item_show_func=item_show_func,
                        write=lambda line: click.echo(line, file=stream), interval_s=interval_s, clock=clock)  # fmt: skip


@contextlib.contextmanager
def counted(label: str, write: Callable[[str], None] | None = None, *, file: IO | None = None,
            item_show_func: Callable[[Any], str | None] | None = None, interval_s: float = PROGRESS_LINE_INTERVAL_S,
            clock: Callable[[], float] = time.monotonic) -> Iterator[Callable[..., None]]:  # fmt: skip
    """``progress(done, total=None, item=None)`` for a library loop that reports counts (and what it works on, shown by
    ``item_show_func``): ``LineProgress`` lines to ``write``, or without it ``progressbar`` on ``file`` (default
    stderr; a total-less count there is in lines too). The total may change between reports.

    The bar opens with the first report, so work that fails before it (an unreadable input) or has nothing to do
    (a cache hit) shows none; the end line follows only a loop that reported and ended without an error.
    """
    bar = None

    def progress(done: int, total: int | None = None, item: Any = None) -> None:
        nonlocal bar
        if bar is None:
            stream = sys.stderr if file is None else file
            if write is None and total is not None:
                bar = progressbar(length=total, label=label, item_show_func=item_show_func, file=stream,
                                  interval_s=interval_s, clock=clock)  # fmt: skip
            else:
                out = write if write is not None else (lambda line: click.echo(line, file=stream))
                bar = LineProgress(length=total, label=label, item_show_func=item_show_func, write=out,
                                   interval_s=interval_s, clock=clock)  # fmt: skip
            bar.__enter__()
        if total is not None:
            bar.length = total
        bar.update(done - bar.pos, item)

    try:
        yield progress
    except BaseException as e:
        if bar is not None:  # click's bar ends its line; LineProgress writes nothing
            bar.__exit__(type(e), e, e.__traceback__)
        raise
    if bar is not None:
        bar.__exit__(None, None, None)


def _duration(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, s = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes} min {s:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


class LineProgress:
    """A progress report in plain lines given to ``write``: one at the start, one per ``interval_s`` while steps are
    made, one at the end.

    ``length`` may be unknown (None) or set later, as click's bar allows; with neither an iterable nor a length it
    counts the steps given to ``update`` (a stream of unknown length). A loop left by an exception writes no end
    line (the error that follows says why it stopped).
    """

    def __init__(self, iterable: Iterable | None = None, *, length: int | None = None, label: str,
                 item_show_func: Callable[[Any], str | None] | None = None, write: Callable[[str], None],
                 interval_s: float = PROGRESS_LINE_INTERVAL_S, clock: Callable[[], float] = time.monotonic) -> None:  # fmt: skip
        if not interval_s > 0:
            raise ValueError(f"interval_s must be > 0 seconds, got {interval_s!r}")
        if length is None:
            try:
                length = len(iterable)  # type: ignore[arg-type]
            except TypeError:  # a generator: the count stays unknown
                length = None
        self.iterable = range(length) if iterable is None and length is not None else iterable  # None: a count alone
        self.length = length
        self.label = label
        self.item_show_func = item_show_func
        self.write = write
        self.interval_s = interval_s
        self.clock = clock
        self.pos = 0
        self.current_item: Any = None
        self._start = self._last = clock()
        self._started = False

    def __enter__(self) -> LineProgress:
        self._start = self._last = self.clock()
        if not self._started:
            self._started = True
            total = f" ({self.length} step{'' if self.length == 1 else 's'})" if self.length is not None else ""
            self.write(f"{self.label}{total}")
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            done = f"{self.pos}/{self.length}" if self.length is not None else f"{self.pos}"
            self.write(f"{self.label}: {done} done in {_duration(self.clock() - self._start)}")

    def __iter__(self) -> Iterator:
        if not self._started:
            raise RuntimeError("iterate a progressbar inside its `with` block")
        if self.iterable is None:
            raise TypeError(f"{self.label!r} counts steps given to update(): it has nothing to iterate")
        for item in self.iterable:
            self.current_item = item
            yield item
            self.update(1)

    def update(self, n_steps: int, current_item: Any = None) -> None:
        self.pos += n_steps
        if current_item is not None:
            self.current_item = current_item
        now = self.clock()
        if now - self._last >= self.interval_s:
            self._last = now
            self.write(self._line(now - self._start))

    def _line(self, elapsed_s: float) -> str:
        parts = [f"{self.label}: {self.pos}"]
        if self.length:
            parts[0] += f"/{self.length} ({100 * self.pos // self.length} %)"
        parts.append(_duration(elapsed_s))
        if self.length and 0 < self.pos < self.length:
            parts.append(f"about {_duration(elapsed_s * (self.length - self.pos) / self.pos)} left")
        item = self.item_show_func(self.current_item) if self.item_show_func is not None else None
        if item:
            parts.append(str(item))
        return ", ".join(parts)
