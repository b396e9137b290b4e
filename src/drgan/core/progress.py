"""What a long stage is doing and how long it has left, for a person watching and for the pipeline.

A stage reports its work as tasks (``"rendering pairs"``, ``"training"``, ...) with a count done of a total. Each report
goes to two places:

- **the console**, when it is not a terminal (a log file, the pipeline's child, a SLURM job: tqdm's and Rich's bars
  write nothing useful there): one plain line every ``DRGAN_PROGRESS_EVERY`` seconds (default 60) and one when a
  task ends, e.g. ``progress: generate: rendering pairs 420/1000 pairs (42 %), 3.1 min so far, ~4.3 min left``. On a
  terminal the stages' own bars show the same and these lines stay quiet.
- **a progress file**, when ``DRGAN_PROGRESS`` names one (the pipeline sets it for each stage): a small JSON of the
  latest report (task, done, total, unit, seconds so far, estimated seconds left), rewritten atomically at most every
  2 s. The pipeline reads it for its own line, which adds the estimated end of the whole run.

The estimate is the task's own rate so far (wall time per unit since the task started, its first unit excluded
when it paid start-up costs): honest for the steady loops the stages run (renders, training steps, images).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypeVar

from drgan.core.io import atomic_path

T = TypeVar("T")

FILE_ENV = "DRGAN_PROGRESS"  # the progress file of this process's stage (set by the pipeline)
EVERY_ENV = "DRGAN_PROGRESS_EVERY"  # seconds between console lines when the console is not a terminal
STAGE_ENV = "DRGAN_STAGE"  # the stage's name in the lines (set by the pipeline; else the task alone)
FILE_INTERVAL_S = 2.0


@dataclass
class Report:
    """The latest state of one task: what it is, how far, how long so far and (once known) how long it has left."""

    task: str
    done: float
    total: float | None
    unit: str
    seconds: float
    left_s: float | None
    stage: str | None = None
    finished: bool = False

    def counted(self) -> str:
        """``rendering pairs 420/1000 pairs``."""
        count = f"{_count_text(self.done)}/{_count_text(self.total)}" if self.total else _count_text(self.done)
        return f"{self.task} {count}" + (f" {self.unit}" if self.unit else "")

    def share(self) -> str:
        """`` (42 %)``, or "" without a total."""
        return f" ({100 * self.done / self.total:.0f} %)" if self.total else ""

    def line(self) -> str:
        """``generate: rendering pairs 420/1000 pairs (42 %), 3.1 min so far, ~4.3 min left``."""
        left = "done" if self.finished else ("~" + duration(self.left_s) + " left" if self.left_s is not None else "")
        parts = [f"{self.counted()}{self.share()}", f"{duration(self.seconds)} so far", left]
        return (f"{self.stage}: " if self.stage else "") + ", ".join(p for p in parts if p)


def _count_text(value: float | None) -> str:
    if value is None:
        return "?"
    return f"{value:.0f}" if float(value).is_integer() or value >= 10 else f"{value:.1f}"


def duration(seconds: float | None) -> str:
    """Seconds as a person reads them: ``45 s``, ``6.3 min``, ``1.4 h``."""
    if seconds is None or not math.isfinite(seconds):
        return "?"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def estimate_left(done: float, total: float | None, seconds: float, first_unit_s: float | None = None) -> float | None:
    """Seconds left at the rate so far; ``first_unit_s``: the first unit's time, left out of the rate when more units
    have been done (it carries start-up work: a network's first pass, caches)."""
    if not total or done <= 0 or done >= total:
        return 0.0 if total and done >= total else None
    if first_unit_s is not None and done > 1 and seconds > first_unit_s:
        rate = (seconds - first_unit_s) / (done - 1)
    else:
        rate = seconds / done
    return max(0.0, rate * (total - done))


def read_report(path: str | os.PathLike) -> Report | None:
    """The progress file's latest report (None when missing or being replaced)."""
    try:
        data = json.loads(Path(path).read_text())
        return Report(**{k: data.get(k) for k in Report.__dataclass_fields__})
    except (OSError, ValueError, TypeError):
        return None


class Task:
    """One task's progress: ``update(done)`` or ``advance(n)`` as work is done, ``close()`` when it ends (also as a
    context manager). ``total``: the units it will do (None: unknown, no estimate); ``start``: units already done
    before this process (a resumed job), counted as done but not in the rate."""

    def __init__(self, task: str, total: float | None = None, unit: str = "", start: float = 0.0):
        self.task, self.total, self.unit = task, total, unit
        self.done = float(start)
        self._offset = float(start)
        self._begin = time.perf_counter()
        self._first: float | None = None
        self._file = os.environ.get(FILE_ENV) or None
        self._every = _every()
        self._quiet = _is_terminal()
        self._last_file = -math.inf
        self._last_line = time.perf_counter()
        self.stage = os.environ.get(STAGE_ENV) or None

    def report(self, finished: bool = False) -> Report:
        seconds = time.perf_counter() - self._begin
        own = self.done - self._offset
        own_total = None if self.total is None else self.total - self._offset
        left = 0.0 if finished else estimate_left(own, own_total, seconds, self._first)
        return Report(self.task, self.done, self.total, self.unit, seconds, left, self.stage, finished)

    def update(self, done: float) -> None:
        now = time.perf_counter()
        if self._first is None and done > self._offset:
            self._first = now - self._begin
        self.done = float(done)
        if self._file and now - self._last_file >= FILE_INTERVAL_S:
            self._write(self.report())
            self._last_file = now
        if not self._quiet and self._every > 0 and now - self._last_line >= self._every:
            self._print(self.report())
            self._last_line = now

    def advance(self, n: float = 1) -> None:
        self.update(self.done + n)

    def close(self) -> None:
        report = self.report(finished=True)
        if self._file:
            self._write(report)
        if not self._quiet and self._every > 0:
            self._print(report)

    def __enter__(self) -> Task:
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()

    def _write(self, report: Report) -> None:
        try:
            with atomic_path(self._file) as tmp:
                tmp.write_text(json.dumps({**asdict(report), "updated": time.time()}))
        except OSError:  # progress is for watching: a full disk or a removed folder must not stop the work
            pass

    @staticmethod
    def _print(report: Report) -> None:
        print(f"progress: {report.line()}", file=sys.stderr, flush=True)


def track(items: Iterable[T], task: str, total: float | None = None, unit: str = "", start: float = 0.0,
          bar: bool = True) -> Iterator[T]:  # fmt: skip
    """Iterate ``items`` reporting each one done (``total`` defaults to ``len(items)``); ``bar``: also tqdm's bar on
    a terminal (as the stages showed before)."""
    if total is None and hasattr(items, "__len__"):
        total = len(items) + start  # type: ignore[arg-type]
    progress = Task(task, total, unit, start)
    iterator: Iterable[T] = items
    if bar and _is_terminal():
        from tqdm import tqdm

        iterator = tqdm(items, desc=task, unit=unit or "it", total=None if total is None else total - start)
    for item in iterator:
        yield item
        progress.advance()
    progress.close()


def _every() -> float:
    text = os.environ.get(EVERY_ENV)
    try:
        return 60.0 if text is None else float(text)
    except ValueError:
        return 60.0


def _is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False
