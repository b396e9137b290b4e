"""The pipeline's local runner: each stage not done runs as its own command, one after another (the overview, what a
user reads in ``--help``: drgan.pipeline's docstring)."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence

from drgan.core.errors import ConfigError, DrganError
from drgan.core.progress import EVERY_ENV, STAGE_ENV
from drgan.core.progress import FILE_ENV as PROGRESS_FILE_ENV
from drgan.pipeline import progress_line
from drgan.pipeline.report import write_report
from drgan.pipeline.settings import CONFIG, REPORT_FILE, STATE_FILE, Settings, parse_settings
from drgan.pipeline.stage_table import profiled_pixel_size
from drgan.pipeline.stages import (
    Stage,
    build_stages,
    check_inputs,
    check_stage_settings,
    done_after_pending,
    forget,
    is_done,
    prepare_redo,
    stale_check,
)
from drgan.pipeline.submit import status_lines, submit_run
from drgan.pipeline.tracking import State, Tracker, folder_lock

log = logging.getLogger("drgan.pipeline")

# --- running ---------------------------------------------------------------------------------------------


class Terminated(KeyboardInterrupt):
    """SIGTERM (scancel, a job's time limit, kill): stopped as a Ctrl-C is, the stage's child stopped too."""


def _terminate(signum, frame):
    raise Terminated()


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """While inside: a SIGTERM raises Terminated (the stage stopped cleanly, the state and report written)."""
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _die_with_parent() -> None:
    """In the child, before exec: a SIGKILL of the pipeline kills the stage too (Linux), so that a rerun never
    finds the old stage still writing into its folder."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def run_stage(stage: Stage, env: Mapping[str, str] | None = None, every: float = 0.0,
              tick: Callable[[], None] | None = None) -> int:  # fmt: skip
    """Run one stage's command, its output on this console; the exit code. ``tick()`` every ``every`` seconds while
    it runs (the progress line; 0: never)."""
    process = subprocess.Popen(stage.command(), env=dict(env or os.environ), preexec_fn=_die_with_parent)
    try:
        while True:
            try:
                return process.wait(timeout=every if every > 0 and tick is not None else None)
            except subprocess.TimeoutExpired:
                tick()
    except KeyboardInterrupt as stop:  # the stage got the same Ctrl-C (one process group): let it stop cleanly
        if isinstance(stop, Terminated):  # a SIGTERM may have been this process's alone: pass it on
            process.terminate()
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
        raise


def run(s: Settings, echo: Callable[[str], None] = print) -> dict:
    """Run (or resume) the pipeline of ``s``; returns pipeline.json's content. ``launcher=slurm`` submits its stages
    as jobs instead (drgan.pipeline.submit) and returns at once; ``only=STAGE`` runs that one stage (what each job
    does), ``only=generate shard=i/N`` one shard of its pairs (a job array's task)."""
    if s.launcher == "slurm":
        submit_run(s, echo)
        return State(s.out / STATE_FILE).data
    if s.shard is not None:
        return _run_shard(s, echo)
    inputs = check_inputs(s)
    check_stage_settings(s)
    with _sigterm_as_interrupt(), folder_lock(s.out, wait=LOCK_WAIT_S if s.only else 0.0):
        return _run_locked(s, inputs, echo)


LOCK_WAIT_S = 300.0  # only=STAGE (a SLURM job) waits this long for the folder's lock: its submission may still hold it


def _run_locked(s: Settings, inputs: dict, echo: Callable[[str], None]) -> dict:
    state = State(s.out / STATE_FILE)
    state.data.update({"data_dir": str(s.data_dir), "name": s.name, "inputs": inputs,
                       "annotated": str(s.annotated) if s.annotated else None})  # fmt: skip
    tracker = Tracker(s)
    stages = build_stages(s, tracker.parent)
    prepare_redo(s, state, stages)
    if s.only is None:
        for stage in done_after_pending(stages, state):
            echo(f"pipeline: {stage.name} is done, but a stage before it will run: {stage.name} runs again after it")
            forget(stage, state)
    names = [st.name for st in stages]
    if s.only is not None and s.only not in names:
        raise ConfigError(f"pipeline: only={s.only}: this run has no such stage (its stages: {', '.join(names)})")
    last = names.index(s.only) if s.only else len(stages) - 1
    total, started = len(stages), time.perf_counter()
    status = "FAILED"
    try:
        for number, stage in enumerate(stages[: last + 1], 1):
            # its arguments again, now with what the stages before it found (the profile's pixel size)
            # (kept in `stages`, so that report.md shows the command as it ran)
            stage = stages[number - 1] = build_stages(s, tracker.parent, profiled_pixel_size(s.out))[number - 1]
            record = state.stage(stage.name)
            if is_done(stage, record):
                stale_check(stage, record)
                if s.only is None or stage.name == s.only:
                    echo(f"[{number}/{total}] {stage.name}: done ({_minutes(record.get('seconds'))}), skipped")
                continue
            if s.only is not None and stage.name != s.only:
                raise DrganError(
                    f"pipeline: only={s.only}: the stage before it, {stage.name}, is not done (run it first: "
                    f"only={stage.name}, or the whole pipeline without only=)"
                )
            _run_one(s, stage, number, stages, state, tracker, echo)
            write_report(s, state.data, stages)
        status = "FINISHED" if last == len(stages) - 1 else "RUNNING"
    except KeyboardInterrupt:
        status = "KILLED"
        echo("pipeline: interrupted; run the same command again to resume")
        raise
    finally:
        write_report(s, state.data, stages)
        tracker.finish(status, {"time/wall_s": time.perf_counter() - started} if s.only is None else {})
    echo(f"pipeline {s.name}: {'done' if status == 'FINISHED' else f'{s.only} done'}; the report: "
         f"{s.out / REPORT_FILE}")  # fmt: skip
    return state.data


def _run_one(s: Settings, stage: Stage, number: int, stages: list[Stage], state: State, tracker: Tracker,
             echo: Callable[[str], None]) -> None:  # fmt: skip
    record = state.stage(stage.name)
    total = len(stages)
    resumed = record.get("state") not in (None, "submitted") or bool(stage.resume())
    echo(f"[{number}/{total}] {stage.name}: {'resuming' if resumed else 'starting'} (folder {stage.folder})")
    state.update(stage.name, state="running", args=stage.recorded(), started=time.time(),
                 job=os.environ.get("SLURM_JOB_ID") if s.only else None)  # fmt: skip
    begin = time.perf_counter()
    watch = _Watch(stages, state, number, begin, echo)
    code = run_stage(stage, watch.environment(), s.progress, watch.tick)
    seconds = time.perf_counter() - begin + float(record.get("seconds_before") or 0.0)
    if code != 0:
        state.update(stage.name, state="failed", exit_code=code, seconds_before=seconds)
        raise DrganError(
            f"pipeline: stage {stage.name} failed (exit code {code}; its message is above, its log in "
            f"{stage.folder}); fix what it says and run the same command again to resume"
        )
    if not stage.done_file.is_file():
        state.update(stage.name, state="failed", exit_code=code, seconds_before=seconds)
        raise DrganError(f"pipeline: stage {stage.name} exited 0 but wrote no {stage.done_file}")
    summary = stage.spec.summary(stage.folder)
    state.update(stage.name, state="done", seconds=seconds, seconds_before=None, finished=time.time(),
                 summary=summary)  # fmt: skip
    if not stage.spec.mlflow_run:  # a stage with an MLflow run of its own (train, segment) logs itself
        tracker.child(stage, seconds, _numbers(summary), [stage.folder / n for n in stage.spec.artifacts])
    echo(f"[{number}/{total}] {stage.name}: done in {_minutes(seconds)}"
         + (f": {summary['line']}" if summary.get("line") else ""))  # fmt: skip


def _run_shard(s: Settings, echo: Callable[[str], None]) -> dict:
    """``only=generate shard=i/N``: this shard's pairs into the generate folder (drgan.generate shares the folder
    between shards); no lock, no state: the job after the array completes the set as the stage."""
    state = State(s.out / STATE_FILE)
    stages = build_stages(s, None, profiled_pixel_size(s.out))
    train = next(st for st in stages if st.name == "train")
    if not is_done(train, state.stage("train")):
        raise DrganError(f"pipeline: shard={s.shard}: the GAN (stage train) is not done in {s.out}")
    stage = next(st for st in stages if st.name == "generate")
    shard_stage = Stage(stage.spec, stage.folder, stage.wired, [*stage.settings, f"shard={s.shard}"],
                        stage.done_file)  # fmt: skip
    echo(f"generate: shard {s.shard} (folder {stage.folder})")
    with _sigterm_as_interrupt():
        code = run_stage(shard_stage, {**os.environ, EVERY_ENV: str(s.progress)})
    if code != 0:
        raise DrganError(f"pipeline: generate shard {s.shard} failed (exit code {code}; its message is above)")
    return state.data


class _Watch:
    """The running stage's progress file (passed to it as DRGAN_PROGRESS) and the pipeline's line from it."""

    def __init__(self, stages: list[Stage], state: State, number: int, begin: float, echo: Callable[[str], None]):
        self.stages, self.state, self.number, self.begin, self.echo = stages, state, number, begin, echo
        self.stage = stages[number - 1]
        progress_line.progress_file(self.stage.folder).unlink(missing_ok=True)  # a killed attempt's last report

    def environment(self) -> dict[str, str]:
        return {
            **os.environ,
            PROGRESS_FILE_ENV: str(progress_line.progress_file(self.stage.folder)),
            STAGE_ENV: self.stage.name,
            EVERY_ENV: "0",
        }  # fmt: skip  (the pipeline's line says it instead)

    def tick(self) -> None:
        done = [(60.0 * st.spec.typical_minutes, float(self.state.stage(st.name).get("seconds") or 0.0))
                for st in self.stages[: self.number - 1] if st.spec.paced and self.state.stage(st.name).get("seconds")]  # fmt: skip
        factor = progress_line.pace(done)
        report = progress_line.read(self.stage.folder)
        elapsed = time.perf_counter() - self.begin
        own = factor if self.stage.spec.paced else 1.0
        left = progress_line.stage_left(report, 60.0 * self.stage.spec.typical_minutes, elapsed, own)
        later = [
            60.0 * st.spec.typical_minutes * (factor if st.spec.paced else 1.0) for st in self.stages[self.number :]
        ]
        run_left = progress_line.whole_left(left, later)
        self.echo(progress_line.line(self.number, len(self.stages), self.stage.name, report, elapsed, left, run_left))


def _numbers(summary: dict) -> dict[str, float]:
    return {k: v for k, v in (summary.get("metrics") or {}).items() if isinstance(v, (int, float))}


def _minutes(seconds) -> str:
    if not isinstance(seconds, (int, float)):
        return "time unknown"
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


# --- command line ---------------------------------------------------------------------------------------------


def help_text() -> str:
    from drgan.launch.runtime import stage_help

    overview = sys.modules["drgan.pipeline"].__doc__ or ""
    return (
        f"{stage_help('python -m drgan.pipeline', overview, CONFIG, 'conf/pipeline/pipeline.yaml')}\n"
        "Each stage's own keys: drgan STAGE --help (e.g. drgan train --help)."
    )


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help") for a in argv):
        with contextlib.suppress(BrokenPipeError):  # `... --help | head`: the reader left
            print(help_text(), flush=True)
        return 0
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s", datefmt="%H:%M:%S")
    status = "status" in argv  # `... status`: each stage's state (and SLURM job), nothing run
    argv = [a for a in argv if a != "status"]
    try:
        from drgan.pipeline import batch

        if batch.is_batch(argv):
            if status:
                study = batch.parse_batch(argv)
                for sample in study.samples:
                    print("\n".join(status_lines(batch.sample_settings(study, sample, None))))
                return 0
            batch.run_batch(argv, run)
        elif status:
            print("\n".join(status_lines(parse_settings(argv))))
        else:
            run(parse_settings(argv))
    except DrganError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
