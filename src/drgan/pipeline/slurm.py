"""``launcher=slurm``: a pipeline run's stages as SLURM jobs, each with its own resources, chained with sbatch's
``--dependency=afterok`` so that a stage starts only after the one before it succeeded.

Submission (on the login node, in seconds): every check a local run makes (the folder, the stage keys), then that
``sbatch``, ``squeue`` and ``scontrol`` are on the PATH, that every partition named exists and that every stage's
request fits the cluster (``sbatch --test-only``, which submits nothing), all before the first job is submitted. Then
one job per stage that is not done, each running ``python -m drgan.pipeline ... launcher=local only=STAGE``: the same
runner a local run uses, for that one stage, in the same folders, with the same pipeline.json states, resume rules and
report.md. Its console goes to ``OUT/slurm/STAGE-JOBID.log``. The jobs after a failed one are cancelled by SLURM
(``--kill-on-invalid-dep=yes``); the same command again submits the stages that are not done, and a stage whose job
was cancelled or timed out mid-way resumes from its last checkpoint, exactly as after a local kill. With
``slurm.shards=N`` the generate stage is a job array of N shards (``generate shard=i/N``, each task a share of the
pairs, into one folder), then one short job that completes the set as the single-process generate does.

We call sbatch ourselves rather than submitit: submitit ships each job as a pickled function, and drgan never loads a
pickle that can run code; a job here is a two-line shell script anyone can read and resubmit by hand.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from drgan.core.errors import ConfigError
from drgan.core.io import write_bytes

RESOURCE_KEYS = ("cpus", "mem", "gpus", "time", "partition")
GENERAL_KEYS = ("partition", "account", "qos", "options", "shards")
TOOLS = ("sbatch", "squeue", "scontrol")
ACTIVE = {"PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "SUSPENDED", "REQUEUED", "RESIZING", "SIGNALING",
          "STAGE_OUT", "REQUEUE_HOLD", "REQUEUE_FED", "RESV_DEL_HOLD", "STOPPED"}  # fmt: skip
_MEM = re.compile(r"^\d+[KMGT]?$")
_TIME = re.compile(r"^(\d+-)?\d+(:\d{1,2}){0,2}$")  # sbatch --time: MM, MM:SS, HH:MM:SS, D-HH[:MM[:SS]]


@dataclass(frozen=True)
class Resources:
    """One stage's request: CPUs (one task), memory (sbatch --mem), GPUs (--gpus), wall-time limit, partition."""

    cpus: int = 1
    mem: str = "8G"
    gpus: int = 0
    time: str = "1:00:00"
    partition: str | None = None

    def options(self) -> list[str]:
        return [f"--cpus-per-task={self.cpus}", f"--mem={self.mem}", f"--time={self.time}",
                *([f"--gpus={self.gpus}"] if self.gpus else []),
                *([f"--partition={self.partition}"] if self.partition else [])]  # fmt: skip


@dataclass(frozen=True)
class SlurmSettings:
    """conf/pipeline/pipeline.yaml's ``slurm:`` block with the command line's ``slurm.KEY=VALUE`` words."""

    stages: Mapping[str, Resources]
    account: str | None = None
    qos: str | None = None
    options: tuple[str, ...] = ()
    shards: int = 1

    def job_options(self, stage: str) -> list[str]:
        return [*self.stages[stage].options(), *([f"--account={self.account}"] if self.account else []),
                *([f"--qos={self.qos}"] if self.qos else []), *self.options]  # fmt: skip


def _null(value) -> bool:
    return value is None or str(value) in ("null", "None", "")


def _resources(stage: str, values: Mapping, partition) -> Resources:
    unknown = sorted(set(values) - set(RESOURCE_KEYS))
    if unknown:
        raise ConfigError(
            f"pipeline: slurm.{stage}.{unknown[0]}: not a resource key (the keys of a stage: {', '.join(RESOURCE_KEYS)})"
        )
    merged = {"partition": partition, **values}
    try:
        cpus, gpus = int(str(merged.get("cpus", 1))), int(str(merged.get("gpus", 0)))
    except ValueError:
        raise ConfigError(
            f"pipeline: slurm.{stage}: cpus={merged.get('cpus')!r}, gpus={merged.get('gpus')!r}: expected whole "
            "numbers (cpus >= 1, gpus >= 0)"
        ) from None
    mem, time = str(merged.get("mem", "8G")), str(merged.get("time", "1:00:00"))
    if cpus < 1 or gpus < 0:
        raise ConfigError(f"pipeline: slurm.{stage}: cpus={cpus}, gpus={gpus}: expected cpus >= 1 and gpus >= 0")
    if not _MEM.match(mem):
        raise ConfigError(f"pipeline: slurm.{stage}.mem={mem!r}: expected sbatch's --mem, e.g. 16G or 4000M")
    if not _TIME.match(time):
        raise ConfigError(
            f"pipeline: slurm.{stage}.time={time!r}: expected sbatch's --time, e.g. 4:00:00 (HH:MM:SS), 90 (minutes) "
            "or 1-00:00:00 (a day)"
        )
    part = merged.get("partition")
    return Resources(cpus, mem, gpus, time, None if _null(part) else str(part))


def parse_slurm(base: Mapping, words: Mapping[str, str], stages: Sequence[str]) -> SlurmSettings:
    """``base``: the YAML's ``slurm:`` block; ``words``: ``slurm.KEY=VALUE`` of the command line, the ``slurm.``
    prefix removed (``partition``, ``shards``, ``gpus`` for every stage, ``train.gpus`` for one). A stage's request is
    the YAML's, then the command line's for every stage, then the command line's for that stage. Unknown keys and bad
    values are refused here."""
    general = {k: base.get(k) for k in GENERAL_KEYS}
    per_stage: dict[str, dict] = {s: dict((base.get("stages") or {}).get(s) or {}) for s in stages}
    every: dict[str, str] = {}
    own: dict[str, dict] = {s: {} for s in stages}
    for key, value in words.items():
        head, dot, rest = key.partition(".")
        if not dot and head in GENERAL_KEYS:
            general[head] = value
        elif not dot and head in RESOURCE_KEYS:
            every[head] = value
        elif dot and head in per_stage and "." not in rest:
            own[head][rest] = value
        else:
            raise ConfigError(
                f"pipeline: slurm.{key}: not a SLURM setting (slurm.KEY with KEY one of "
                f"{', '.join(dict.fromkeys([*GENERAL_KEYS, *RESOURCE_KEYS]))}, or slurm.STAGE.KEY with STAGE one of "
                f"{', '.join(stages)} and KEY one of {', '.join(RESOURCE_KEYS)})"
            )
    options = general.get("options") or ()
    if isinstance(options, str):
        options = [o.strip() for o in options.strip("[]").split(",") if o.strip()]
    try:
        shards = int(str(general.get("shards") or 1))
    except ValueError:
        shards = 0
    if shards < 1:
        raise ConfigError(f"pipeline: slurm.shards={general.get('shards')!r}: expected a whole number >= 1")
    partition = general.get("partition")
    return SlurmSettings(
        stages={s: _resources(s, {**values, **every, **own[s]}, partition) for s, values in per_stage.items()},
        account=None if _null(general.get("account")) else str(general["account"]),
        qos=None if _null(general.get("qos")) else str(general["qos"]),
        options=tuple(str(o) for o in options),
        shards=shards,
    )


# --- the scheduler -----------------------------------------------------------------------------------------


def require_tools() -> None:
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if missing:
        raise ConfigError(
            f"pipeline: launcher=slurm: {', '.join(missing)} not on the PATH; run it where SLURM's commands are (a "
            "login node; `module load slurm` on some clusters), or launcher=local to run every stage here"
        )


def _call(args: Sequence[str], what: str) -> str:
    result = subprocess.run(list(args), capture_output=True, text=True)
    if result.returncode != 0:
        message = (result.stderr or result.stdout).strip().splitlines()
        raise ConfigError(f"pipeline: {what}: {message[-1] if message else f'exit code {result.returncode}'}")
    return result.stdout


def partitions() -> set[str]:
    """The cluster's partitions (scontrol show partition; sinfo marks the default with a *)."""
    text = _call(["scontrol", "-o", "show", "partition"], "scontrol show partition")
    return set(re.findall(r"PartitionName=(\S+)", text))


def check_requests(settings: SlurmSettings, stages: Sequence[str], workdir: Path) -> None:
    """Every partition named exists, and every stage's request could run (``sbatch --test-only``: nothing is
    submitted); else a ConfigError naming the stage and the scheduler's reason."""
    known = partitions()
    for stage in stages:
        part = settings.stages[stage].partition
        if part is not None and part not in known:
            raise ConfigError(
                f"pipeline: slurm.{stage}.partition={part}: no such partition on this cluster "
                f"(it has: {', '.join(sorted(known)) or 'none'}); set slurm.partition= or slurm.{stage}.partition="
            )
    for stage in stages:
        args = ["sbatch", "--test-only", f"--chdir={workdir}", *settings.job_options(stage), "--wrap", "true"]
        result = subprocess.run(args, capture_output=True, text=True)
        if result.returncode != 0:
            reason = (result.stderr or result.stdout).strip().splitlines()
            raise ConfigError(
                f"pipeline: the {stage} stage's SLURM request ({' '.join(settings.job_options(stage))}) cannot run "
                f"here: {reason[-1] if reason else 'sbatch --test-only failed'}; change slurm.{stage}.* (e.g. "
                f"slurm.{stage}.gpus=0 on a cluster without GPUs)"
            )


def job_script(path: Path, workdir: Path, command: Sequence[str], tail: str = "") -> Path:
    """A readable job script: the threads set to the job's CPUs, cd to the submission's folder, then the command
    (exec'd: the job is that process);
    ``tail``: shell words appended as they are (an array task's ``"shard=${SLURM_ARRAY_TASK_ID}/N"``)."""
    text = (
        "#!/bin/bash\n# written by drgan.pipeline (launcher=slurm); resubmit by hand with sbatch if you like\n"
        "# the job's CPUs for torch's and NumPy's threads (where the submitting shell set none)\n"
        'export OMP_NUM_THREADS="${OMP_NUM_THREADS:-${SLURM_CPUS_PER_TASK:-1}}"\n'
        f"cd {shlex.quote(str(workdir))}\nexec {shlex.join(command)}{' ' + tail if tail else ''}\n"
    )
    write_bytes(path, text.encode())
    path.chmod(0o755)
    return path


def submit(script: Path, name: str, options: Sequence[str], log: str, workdir: Path,
           after: Sequence[str] = (), condition: str = "afterok", array: str | None = None) -> str:  # fmt: skip
    """Submit ``script``; its job id. ``after``: the job ids it waits for (``condition``: afterok, afterany)."""
    args = ["sbatch", "--parsable", f"--job-name={name}", f"--output={log}", f"--chdir={workdir}", *options]
    if after:
        args += [f"--dependency={condition}:{':'.join(after)}", "--kill-on-invalid-dep=yes"]
    if array:
        args.append(f"--array={array}")
    out = _call([*args, str(script)], f"sbatch {script.name}")
    return out.strip().split(";")[0]


@dataclass(frozen=True)
class JobState:
    state: str  # SLURM's: PENDING, RUNNING, COMPLETED, FAILED, CANCELLED, TIMEOUT, ...; UNKNOWN when forgotten
    elapsed: str = ""
    exit_code: str = ""
    reason: str = ""

    @property
    def active(self) -> bool:
        return self.state in ACTIVE


def job_states(ids: Sequence[str]) -> dict[str, JobState]:
    """SLURM's state of each job (an array: the worst of its tasks), from scontrol (which remembers finished jobs for
    MinJobAge), else sacct (where accounting is on); UNKNOWN where neither knows it."""
    states: dict[str, JobState] = {}
    for job in ids:
        result = subprocess.run(["scontrol", "-o", "show", "job", job], capture_output=True, text=True)
        found = [dict(re.findall(r"(\w+)=(\S*)", line)) for line in result.stdout.splitlines() if line.strip()]
        if result.returncode == 0 and found:
            worst = max(found, key=lambda f: _rank(f.get("JobState", "")))
            states[job] = JobState(worst.get("JobState", "UNKNOWN"), worst.get("RunTime", ""),
                                   worst.get("ExitCode", ""), worst.get("Reason", ""))  # fmt: skip
            continue
        states[job] = _sacct(job) or JobState("UNKNOWN")
    return states


def _rank(state: str) -> int:
    """Which of an array's tasks speaks for it: a failure over a running task over a finished one."""
    if state in ("FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED", "BOOT_FAIL"):
        return 3
    return 2 if state in ACTIVE else 1


def _sacct(job: str) -> JobState | None:
    if shutil.which("sacct") is None:
        return None
    result = subprocess.run(["sacct", "-j", job, "-X", "-n", "-P", "-o", "State,Elapsed,ExitCode"],
                            capture_output=True, text=True)  # fmt: skip
    rows = [line.split("|") for line in result.stdout.splitlines() if line.count("|") == 2]
    if result.returncode != 0 or not rows:
        return None
    state, elapsed, code = max(rows, key=lambda r: _rank(r[0].split()[0]))
    return JobState(state.split()[0], elapsed, code)


def python_command() -> list[str]:
    return [sys.executable, "-m", "drgan.pipeline"]
