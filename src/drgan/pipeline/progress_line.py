"""The pipeline's progress line while a stage runs: what the stage is doing (its own report, drgan.core.progress), its time
left, and the estimated end of the whole run.

The whole run's estimate adds the running stage's time left (its own estimate; before it has one, its typical time
less what it has run) and the later stages' typical times (``StageSpec.typical_minutes``: the defaults on 2 CPU cores,
benchmarks/pipeline.py). The typical times of the stages whose cost is set by their settings (the GAN, generation,
the segmenter) are scaled by this run's own pace: the wall time of those done so far over their typical times (kept
within 1/4-8 x), so that a slower machine lengthens the rest alike; the stages that read every image (profile,
analyze, evaluate: ``StageSpec.paced`` false) neither set the pace nor take it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from drgan.core.progress import Report, duration, read_report

PROGRESS_FILE = "progress.json"
PACE_RANGE = (0.25, 8.0)


def progress_file(folder: Path) -> Path:
    """Where a stage run into ``folder`` reports its progress (the pipeline passes it as DRGAN_PROGRESS)."""
    return folder / PROGRESS_FILE


def pace(done: Sequence[tuple[float, float]]) -> float:
    """This run's pace: the done stages' wall seconds over their typical seconds (``(typical, actual)`` pairs), 1 before
    any; kept within PACE_RANGE (one odd stage must not make the estimate absurd)."""
    typical = sum(t for t, _ in done)
    if typical <= 0:
        return 1.0
    low, high = PACE_RANGE
    return min(high, max(low, sum(a for _, a in done) / typical))


def stage_left(report: Report | None, typical_s: float, elapsed_s: float, factor: float) -> float:
    """The running stage's seconds left: its task's own estimate while a task runs, else (before its first report,
    or between tasks) its scaled typical time less what it has run (not below 0)."""
    if report is not None and not report.finished and report.left_s is not None:
        return float(report.left_s)
    return max(0.0, typical_s * factor - elapsed_s)


def whole_left(current_left_s: float, later_s: Sequence[float]) -> float:
    """The whole run's seconds left: the running stage's and the later stages' expected times (already at pace)."""
    return current_left_s + sum(later_s)


def line(number: int, total: int, stage: str, report: Report | None, elapsed_s: float, left_s: float,
         run_left_s: float, now: float | None = None) -> str:  # fmt: skip
    """``[4/6] segment: training the segmenter 330/1308 steps (25 %), 2.1 min in the stage, ~6.3 min left; the whole
    run: ~12 min left, ends ~01:12 (estimate)``."""
    now = time.time() if now is None else now
    if report is None:
        doing = "running"
    else:
        doing = report.counted() + (" done" if report.finished else report.share())
    end = time.strftime("%H:%M", time.localtime(now + run_left_s))
    return (f"[{number}/{total}] {stage}: {doing}, {duration(elapsed_s)} in the stage, ~{duration(left_s)} left; "
            f"the whole run: ~{duration(run_left_s)} left, ends ~{end} (estimate)")  # fmt: skip


def read(folder: Path) -> Report | None:
    return read_report(progress_file(folder))
