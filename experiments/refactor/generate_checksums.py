"""sha256 of every file a fixed-seed 3-image `python -m drgan.generate` writes, on a tiny checkpoint.

    python experiments/refactor/generate_checksums.py WORK_DIR [--out NAME] [--shards] [--rev GIT_REV]

WORK_DIR/ckpt: a tiny training run (24 px, spp 1, 3 particles, 1 step on hand-made bright discs, no real data),
trained once with `python -m drgan.train` and reused afterwards (delete it to train again). Then
`python -m drgan.generate ckpt=WORK_DIR/ckpt out=WORK_DIR/NAME n=3 n_background=2 seed=0 min_contrast=0` runs
with one torch and one render thread (DRGAN_RENDER_THREADS=1: bitwise repeatable floats in meta/*.json), and
the checksums of every file under WORK_DIR/NAME are printed (relative path, sha256), also of each manifest
without its "throughput" (the only part that times the run) as "NAME#timeless".
--shards: shard=0/2, then shard=1/2, then merge=true (after removing manifest.json) into the same folder.
--rev: run src/drgan/generate.py as it was at GIT_REV (a self-contained file before drgan.dataset existed),
copied under WORK_DIR/rev_GIT_REV with a link to conf/, so one command gives the "before" of a change.
--render: instead, `python -m drgan.render material=M out=WORK_DIR/NAME/M seed=0` at 32 px, spp 4 for both scenes
(tio2_sem: secondary electrons, tio2_tsem: transmission); params.json#timeless is params.json without
"render_seconds". Run it once before and once after a change, from checkouts of each.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

SIZE = 24
GENERATE = ["n=3", "n_background=2", "seed=0", "min_contrast=0", "progress=false"]
RENDER_MATERIALS = ("tio2_sem", "tio2_tsem")
RENDER = ["seed=0", "renderer.resolution=32", "renderer.spp=4"]


def make_images(folder: Path, n: int = 3, size: int = 96) -> None:
    """Bright discs on a dark noisy background (one corner left empty for background patches)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:size, :size]
    for i in range(n):
        img = 0.15 + 0.02 * rng.standard_normal((size, size))
        for _ in range(14):
            cy, cx = rng.uniform(6, size - 6, 2)
            if cy > size - 30 and cx > size - 30:
                continue
            img[(yy - cy) ** 2 + (xx - cx) ** 2 <= 4.5**2] = 0.8
        Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)).save(folder / f"img{i}.png")


def run(args: list[str], env: dict) -> None:
    print("$", " ".join(args), file=sys.stderr, flush=True)
    subprocess.run(args, check=True, env=env, stdout=sys.stderr)


def generate_command(work: Path, rev: str | None) -> list[str]:
    if rev is None:
        return [sys.executable, "-m", "drgan.generate"]
    repo = Path(__file__).resolve().parents[2]
    script = work / f"rev_{rev}" / "pkg" / "drgan" / "generate.py"  # hydra's config_path ../../conf is beside pkg/
    script.parent.mkdir(parents=True, exist_ok=True)
    script.write_bytes(
        subprocess.run(
            ["git", "show", f"{rev}:src/drgan/generate.py"], cwd=repo, check=True, capture_output=True
        ).stdout
    )
    conf = script.parents[2] / "conf"
    if not conf.exists():
        conf.symlink_to(repo / "src" / "drgan" / "conf")  # an old revision: the current configs
    return [sys.executable, str(script)]


def train(work: Path, env: dict) -> Path:
    run_dir = work / "ckpt"
    if (run_dir / "checkpoints" / "best.ckpt").is_file():
        return run_dir
    make_images(work / "real" / "images")
    run(
        [
            sys.executable,
            "-m",
            "drgan.train",
            "debug=fast",
            "material=tio2_sem",
            "material.n_particles=3",
            "material.meshes.count=3",
            f"renderer.resolution={SIZE}",
            "renderer.spp=1",
            "data.view_width=null",  # mine windows of the render size (tiny images)
            f"data.dir={work / 'real' / 'images'}",
            "data.crop_rows=null",
            "data.check_material=false",
            "data.stride=8",
            "data.min_particles=1",
            "data.n_background=2",
            f"paths.output_dir={run_dir}",
            f"paths.root_dir={work}",
            "trainer.accelerator=cpu",
            "trainer.max_epochs=1",
            "trainer.limit_train_batches=1",
            "callbacks.fid.extractor={_target_:drgan.callbacks.RandomProjectionFeatures,dim:16}",
            "callbacks.fid.n_images=4",
            "+callbacks.fid.kid_subsets=5",
            "callbacks.best_epoch.n_phi=20",
            "callbacks.histograms.n_phi=20",
            "callbacks.sample_grid.n=2",
            "callbacks.progress_bar.refresh_rate=0",
        ],
        env,
    )
    return run_dir


def checksums(out: Path) -> dict[str, str]:
    sums = {}
    for path in sorted(p for p in out.rglob("*") if p.is_file()):
        data = path.read_bytes()
        sums[str(path.relative_to(out))] = hashlib.sha256(data).hexdigest()
        if path.name.startswith("manifest") and path.suffix == ".json":
            manifest = json.loads(data)
            manifest.pop("throughput", None)
            timeless = json.dumps(manifest, sort_keys=True).encode()
            sums[f"{path.relative_to(out)}#timeless"] = hashlib.sha256(timeless).hexdigest()
        if path.name == "params.json":
            record = json.loads(data)
            record.pop("render_seconds", None)
            timeless = json.dumps(record, sort_keys=True).encode()
            sums[f"{path.relative_to(out)}#timeless"] = hashlib.sha256(timeless).hexdigest()
    return sums


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--out", default="gen")
    parser.add_argument("--shards", action="store_true", help="two shards, then merge=true")
    parser.add_argument("--rev", help="run generate.py of this git revision")
    parser.add_argument("--render", action="store_true", help="drgan.render of both scenes instead of generate")
    args = parser.parse_args()
    work = args.work.resolve()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "DRGAN_RENDER_THREADS": "1", "HYDRA_FULL_ERROR": "1"}
    if args.render:
        out = work / args.out
        if out.exists():
            sys.exit(f"{out} exists: pick another --out")
        for material in RENDER_MATERIALS:
            run([sys.executable, "-m", "drgan.render", f"material={material}", f"out={out / material}", *RENDER], env)
        for name, digest in checksums(out).items():
            print(f"{digest}  {name}")
        return
    ckpt = train(work, env)
    out = work / args.out
    if out.exists():
        sys.exit(f"{out} exists: pick another --out (a re-run would only resume it)")
    command = [*generate_command(work, args.rev), f"ckpt={ckpt}", f"out={out}", *GENERATE]
    if args.shards:
        run([*command, "shard=0/2"], env)
        run([*command, "shard=1/2"], env)
        (out / "manifest.json").unlink()
        run([*command, "merge=true"], env)
    else:
        run(command, env)
    for name, digest in checksums(out).items():
        print(f"{digest}  {name}")


if __name__ == "__main__":
    main()
