"""The whole chain's wall time, stage by stage, and its end scores: `drgan.pipeline` with its defaults on a fixed set.

    python benchmarks/pipeline.py                          # tio2_tsem: its train ids in, its test ids scored (~30 min)
    python benchmarks/pipeline.py --set tio2_sem --seed 1  # another shared set, another seed
    python benchmarks/pipeline.py --tiny                   # a made-up set of 256-px images of discs, tiny renders (~1 min): that
                                                           # the chain runs and prints every stage (the fast tests)

It runs ``python -m drgan.pipeline data.dir=SET/images annotated=SET`` into ``--out`` (default
runs/benchmarks/pipeline/<set>_<seed>; rerun to resume, ``--fresh`` to start over), then prints a markdown table: each
stage's wall time and share of the whole, what it ended with, and the end scores (evaluate's DSC, AP50, median and
count error on the test ids; the closed-loop check on held-out generated pairs). A change that slows a stage, or costs
a score, shows in it. Wall times are the stages' own (pipeline.json); compare runs made on one machine in one session
(the machines here are shared: repeat, and compare ratios). Recorded tables: experiments/benchmarks/pipeline.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# Tiny renders and one short epoch per stage: the chain's plumbing, not its numbers (as tests/test_pipeline.py's
# slow tiny pipeline). Every stage still runs in its own process with the pipeline's wiring.
TINY = [
    "profile.data.segment.scale=20",  # the discs' size: no scale search
    "train.renderer.resolution=24", "train.renderer.spp=1", "train.data.view_width=null",
    "train.material.n_particles=3", "train.material.n_particles_min=1", "train.material.meshes.count=3",
    "train.data.stride=16", "train.data.min_particles=1", "train.data.n_background=2",
    "train.callbacks.fid.extractor={_target_:drgan.callbacks.RandomProjectionFeatures,dim:16}",
    "train.callbacks.fid.n_images=4", "+train.callbacks.fid.kid_subsets=5", "train.callbacks.best_epoch.n_phi=20",
    "train.callbacks.histograms.n_phi=20", "train.callbacks.sample_grid.n=2", "train.trainer.max_epochs=1",
    "train.data.steps_per_epoch=2", "train.callbacks.grey_start.steps=2", "train.trainer.accelerator=cpu",
    "generate.n=40", "generate.n_background=1", "generate.renderer.spp=1", "generate.sampled_spp=1",
    "generate.min_contrast=1.0",
    "segment.trainer.max_epochs=1", "segment.loader.crop=16", "segment.split_calibration=null",
    "segment.trainer.enable_progress_bar=false", "analyze.inference.tile=64", "evaluate.inference.tile=64",
]  # fmt: skip

SCORES = (  # (stage, metric, label, format)
    ("evaluate", "evaluate/dsc", "test DSC", "{:.3f}"),
    ("evaluate", "evaluate/ap50", "test AP50", "{:.3f}"),
    ("evaluate", "evaluate/median_error", "test median diameter error", "{:+.1%}"),
    ("evaluate", "evaluate/count_error", "test count error", "{:+.1%}"),
    ("segment", "check/median_error", "closed loop median diameter error", "{:+.1%}"),
    ("segment", "check/count_error", "closed loop count error", "{:+.1%}"),
    ("train", "train/best_fid", "GAN best FID", "{:.1f}"),
)


def tiny_set(folder: Path, seed: int = 0, n_train: int = 2, n_test: int = 1, size: int = 256) -> Path:
    """A made-up annotated set: 20 bright discs (diameters lognormal around 20 px, apart) on a dark, grainy film, with
    instance masks and a split."""
    from PIL import Image
    from scipy import ndimage as ndi

    from drgan.core.io import write_json, write_png, write_with

    if folder.exists():
        shutil.rmtree(folder)  # made anew each time: the same set for the same seed
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    ids = [f"t{i}" for i in range(n_train + n_test)]
    for name in ids:
        image, labels, centres = np.full((size, size), 0.2), np.zeros((size, size), np.uint16), []
        for diameter in np.exp(rng.normal(np.log(20.0), 0.25, 20)):
            r = diameter / 2
            for _ in range(200):
                c = rng.uniform(r + 2, size - r - 2, 2)
                if all(np.hypot(*(c - c2)) > r + r2 + 3 for c2, r2 in centres):
                    centres.append((c, r))
                    disc = (yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= r * r
                    image[disc] += 0.5
                    labels[disc] = len(centres)
                    break
        grain = ndi.gaussian_filter(rng.standard_normal((size, size)), 1.0, mode="wrap")
        write_png(folder / "images" / f"{name}.png", (image + 0.03 * grain / grain.std()).clip(0, 1))
        write_with(folder / "masks" / f"{name}.png", lambda f, m=labels: Image.fromarray(m).save(f, format="PNG"))
    write_json(folder / "split.json", {"train": ids[:n_train], "test": ids[n_train:]})
    return folder


def run_pipeline(data: Path, name: str, out: Path, extra: list[str], progress: float) -> int:
    command = [sys.executable, "-m", "drgan.pipeline", f"data.dir={data / 'images'}", f"annotated={data}",
               f"name={name}", f"out={out}", f"progress={progress:g}", *extra]  # fmt: skip
    print("$", " ".join(command), flush=True)
    return subprocess.call(command, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def table(state: dict) -> str:
    """The stage table and the end scores of a pipeline.json."""
    stages = state.get("stages", {})
    seconds = {name: float(record.get("seconds") or 0.0) for name, record in stages.items()}
    total = sum(seconds.values())
    rows = ["| stage | state | wall s | min | share | result |", "|---|---|---|---|---|---|"]
    for name, record in stages.items():
        line = ((record.get("summary") or {}).get("line") or "").replace("|", "/")
        share = f"{seconds[name] / total:.0%}" if total else "n/a"
        rows.append(f"| {name} | {record.get('state')} | {seconds[name]:.0f} | {seconds[name] / 60:.1f} | {share} | "
                    f"{line[:140]} |")  # fmt: skip
    rows.append(f"| **total** | | **{total:.0f}** | **{total / 60:.1f}** | 100% | |")
    scores = ["", "| end score | value |", "|---|---|"]
    for stage, key, label, form in SCORES:
        value = ((stages.get(stage) or {}).get("summary") or {}).get("metrics", {}).get(key)
        scores.append(f"| {label} | {form.format(value) if isinstance(value, (int, float)) else 'n/a'} |")
    return "\n".join(rows + scores)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="tio2_tsem", help="a set under --data (images/, masks/, split.json)")
    ap.add_argument("--data", default=os.environ.get("DRGAN_DATA", "../shared/datasets"))
    ap.add_argument("--seed", type=int, default=0, help="train.seed and segment.seed")
    ap.add_argument("--tiny", action="store_true", help="made-up 256-px images of discs, tiny renders (~1 min)")
    ap.add_argument("--out", type=Path, help="default runs/benchmarks/pipeline/<set>_<seed>")
    ap.add_argument("--fresh", action="store_true", help="remove --out first (else a rerun resumes)")
    ap.add_argument("--progress", type=float, default=60.0, help="seconds between the pipeline's progress lines")
    ap.add_argument("extra", nargs="*", help="more pipeline settings, e.g. segment.trainer.max_epochs=6")
    args = ap.parse_args()

    name = "tiny" if args.tiny else f"bench_{args.set}"
    out = (args.out or Path("runs/benchmarks/pipeline") / f"{'tiny' if args.tiny else args.set}_{args.seed}").resolve()
    if args.fresh and out.exists():
        shutil.rmtree(out)
    if args.tiny:
        data = tiny_set(out.parent / f"{out.name}_set", args.seed)
        extra = ["mlflow=false", *TINY]
    else:
        data = Path(args.data) / args.set
        if not (data / "images").is_dir() or not (data / "split.json").is_file():
            print(f"error: --set {args.set}: expected {data}/images and {data}/split.json (--data: the folder holding "
                  "the shared sets, or DRGAN_DATA)", file=sys.stderr)  # fmt: skip
            return 2
        extra = []
    extra += [f"train.seed={args.seed}", f"segment.seed={args.seed}", *args.extra]
    started = time.perf_counter()
    code = run_pipeline(data.resolve(), name, out, extra, args.progress)
    wall = time.perf_counter() - started
    state_file = out / "pipeline.json"
    if not state_file.is_file():
        print(f"error: the pipeline wrote no {state_file} (exit code {code})", file=sys.stderr)
        return code or 1
    print(f"\n## drgan.pipeline on {'a tiny made-up set' if args.tiny else args.set}, seed {args.seed}: exit code "
          f"{code}, {wall / 60:.1f} min wall in this call (resumed stages count their earlier time in the table)\n")  # fmt: skip
    print(table(json.loads(state_file.read_text())))
    return code


if __name__ == "__main__":
    sys.exit(main())
