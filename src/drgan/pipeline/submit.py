"""A pipeline run submitted to SLURM (``launcher=slurm``: the jobs and their chain, drgan.pipeline.slurm the
scheduler's side), and ``status``: each stage's state, job and progress, for a local run as for a submitted one."""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from drgan.core.errors import ConfigError
from drgan.pipeline import progress_line, slurm
from drgan.pipeline.settings import STATE_FILE, Settings
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
from drgan.pipeline.tracking import State, folder_lock

JOBS_DIR = "slurm"  # OUT/slurm/: the job scripts and their logs (STAGE-JOBID.log)


def job_words(s: Settings, only: str) -> list[str]:
    """The pipeline command a stage's job runs: the user's words without the launcher's own (launcher, redo,
    slurm.*), the inputs as absolute paths, then ``launcher=local only=STAGE``."""
    dropped = {"launcher", "redo", "only", "shard", "data.dir", "name", "annotated", "out"}
    kept = [w for w in s.argv if w.split("=", 1)[0] not in dropped and not w.startswith("slurm.")]
    inputs = [f"data.dir={s.data_dir}", f"name={s.name}", f"out={s.out}",
              *([f"annotated={s.annotated}"] if s.annotated else [])]  # fmt: skip
    return [*slurm.python_command(), *inputs, *kept, "launcher=local", f"only={only}"]


def active_jobs(state: State, stages: Sequence[Stage]) -> dict[str, tuple[str, slurm.JobState]]:
    """The stages whose recorded job (or generate's array) SLURM still runs or queues: stage -> (job, state)."""
    ids = {st.name: [j for j in (state.stage(st.name).get("job"), state.stage(st.name).get("array")) if j]
           for st in stages}  # fmt: skip
    states = slurm.job_states([j for js in ids.values() for j in js]) if any(ids.values()) else {}
    return {name: (job, states[job]) for name, js in ids.items() for job in js if states[job].active}


def refuse_if_submitted(s: Settings) -> None:
    """A run whose jobs SLURM still queues or runs is not submitted twice: the jobs named, and what to do."""
    state = State(s.out / STATE_FILE)
    busy = active_jobs(state, build_stages(s, None, profiled_pixel_size(s.out)))
    if busy:
        listed = ", ".join(f"{name} job {job} {st.state}" for name, (job, st) in busy.items())
        raise ConfigError(
            f"pipeline: {s.name} is submitted already ({listed}); watch it with the same command and `status`, "
            f"or cancel it (scancel {' '.join(job for job, _ in busy.values())}) and submit again"
        )


def submit_run(s: Settings, echo: Callable[[str], None] = print) -> list[str]:
    """Check everything, then submit one job per stage that is not done, chained; the job ids (the last is the
    run's final job)."""
    slurm.require_tools()
    check_inputs(s)
    check_stage_settings(s)
    workdir = Path.cwd()
    refuse_if_submitted(s)  # before the lock: a running job holds it
    with folder_lock(s.out):
        state = State(s.out / STATE_FILE)
        stages = build_stages(s, None, profiled_pixel_size(s.out))
        prepare_redo(s, state, stages)
        for stage in done_after_pending(stages, state):  # (as the local runner: their inputs will change)
            echo(f"pipeline: {stage.name} is done, but a stage before it will run: {stage.name} runs again after it")
            forget(stage, state)
        todo = []
        for stage in stages:
            if is_done(stage, state.stage(stage.name)):
                stale_check(stage, state.stage(stage.name))
                continue
            todo.append(stage)
        if not todo:
            echo(f"pipeline {s.name}: every stage is done; nothing to submit (the report: {s.out / 'report.md'})")
            return []
        requests = slurm_settings(s)
        slurm.check_requests(requests, [st.name for st in todo], workdir)
        folder = s.out / JOBS_DIR
        folder.mkdir(parents=True, exist_ok=True)
        ids: list[str] = []
        previous: list[str] = []
        for stage in todo:
            tag = f"drgan-{s.name}-{stage.name}"
            array = None
            if stage.name == "generate" and requests.shards > 1:
                n = requests.shards
                script = slurm.job_script(folder / "generate-shard.sh", workdir, job_words(s, "generate"),
                                          tail=f'"shard=${{SLURM_ARRAY_TASK_ID}}/{n}"')  # fmt: skip
                array = slurm.submit(script, f"{tag}-shards", requests.job_options("generate"),
                                     str(folder / "generate-shard-%A_%a.log"), workdir, previous,
                                     array=f"0-{n - 1}")  # fmt: skip
                previous = [array]
            script = slurm.job_script(folder / f"{stage.name}.sh", workdir, job_words(s, stage.name))
            options = requests.job_options(stage.name)
            if array is not None:  # the set is rendered: completing it needs one CPU, minutes
                options = [o for o in options if not o.startswith("--gpus")]
            job = slurm.submit(script, tag, options, str(folder / f"{stage.name}-%j.log"), workdir, previous)
            state.update(stage.name, state="submitted", job=job, array=array, submitted=time.time(),
                         log=str(folder / f"{stage.name}-{job}.log"))  # fmt: skip
            ids.append(job)
            previous = [job]
            echo(f"  {stage.name}: job {job}" + (f" (after the {requests.shards} shards of job array {array})"
                                               if array else "") + f"  {' '.join(options)}")  # fmt: skip
        state.data["launcher"] = "slurm"
        state.save()
    echo(f"pipeline {s.name}: {len(ids)} job(s) submitted to SLURM; watch: the same command with `status` "
         f"(or squeue -u $USER); logs in {folder}")  # fmt: skip
    return ids


def slurm_settings(s: Settings) -> slurm.SlurmSettings:
    if s.slurm is None:
        raise ConfigError("pipeline: launcher=slurm without its settings")
    return s.slurm


# --- status ---------------------------------------------------------------------------------------------


def status_lines(s: Settings) -> list[str]:
    """Each stage's state in pipeline.json, with its SLURM job and that job's state where it was submitted, and the
    running stage's latest progress."""
    path = s.out / STATE_FILE
    if not path.is_file():
        return [f"pipeline {s.name}: not started ({path} does not exist)"]
    state = State(path)
    stages = build_stages(s, None, profiled_pixel_size(s.out))
    jobs = [j for st in stages for j in (state.stage(st.name).get("job"), state.stage(st.name).get("array")) if j]
    known = slurm.job_states(jobs) if jobs and shutil.which("scontrol") else {}
    lines = [
        f"pipeline {s.name} ({s.out}):",
        "| stage | state | job | SLURM | elapsed | progress |",
        "|---|---|---|---|---|---|",
    ]
    for stage in stages:
        record = state.stage(stage.name)
        own = "done" if is_done(stage, state.stage(stage.name)) else (record.get("state") or "not started")
        job = record.get("job") or ""
        js = known.get(job)
        array = record.get("array")
        if array and array in known:
            job = f"{job} (shards {array}: {known[array].state})"
        slurm_state = (js.state + (f" ({js.reason})" if js.reason not in ("", "None") else "")) if js else ""
        elapsed = js.elapsed if js else (f"{record['seconds'] / 60:.1f} min" if record.get("seconds") else "")
        report = progress_line.read(stage.folder) if own in ("running", "submitted") else None
        progress = report.line() if report is not None else ""
        lines.append(f"| {stage.name} | {own} | {job} | {slurm_state} | {elapsed} | {progress} |")
    return lines
