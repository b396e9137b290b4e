"""Every bad input of issue 14 and of the README, typed as a user would, with the message drgan gives.

    python experiments/reliability/bad_inputs.py [--only ID,ID] [--keep DIR]

Each row runs one real command line (`python -m drgan.X ...`) in a fresh folder of its own (the working
directory, so runs/ lands there), with tiny data made here where the data are the subject, and the shared
TiO2 SEM images ($DRGAN_DATA, default ../shared/datasets) where they are not: there a late check would first
mine patches from 32 images (20-70 s), which the seconds column would show. For each it prints the last
error line, the work done before the error (read from the files the command left: patches mined, checkpoints,
rendered images, results), and the seconds from start to exit (Python and the imports alone take the first
row's seconds). Prints a Markdown table (experiments/reliability/README.md holds the output).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
from test_train import make_images  # noqa: E402  (tiny synthetic images: bright discs on a dark background)

DATA = Path(os.environ.get("DRGAN_DATA", ROOT.parent / "shared" / "datasets")).resolve()
TINY = [
    "renderer.resolution=24",
    "renderer.spp=1",
    "data.view_width=null",
    "material.n_particles=3",
    "material.meshes.count=3",
    "data.crop_rows=null",
    "data.stride=8",
    "data.min_particles=1",
    "data.n_background=2",
    "logger=none",
]
TINY_FAST = [
    "trainer.max_epochs=1",
    "trainer.limit_train_batches=1",
    "callbacks.best_epoch.n_phi=20",
    "callbacks.histograms.n_phi=20",
    "callbacks.sample_grid.n=2",
    "callbacks.fid.n_images=4",
]


class Crafted:
    """Unpickled without restriction, this would create the file MARKER (the payload of a crafted checkpoint)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@dataclass
class Row:
    id: str
    case: str
    source: str  # issue 14 or README
    args: list[str]  # after `python -m`; {W} is the row's folder, {DATA} the shared data sets
    setup: callable = None
    expect: str = "before"  # what the check should come before (for the reader): "before", "after mining", ...
    env: dict = field(default_factory=dict)


# --- tiny inputs ------------------------------------------------------------------------------------------


def few_images(w: Path) -> None:
    make_images(w / "few", n=3, size=40, seed=2)  # with data.min_particles=2: one 24 px patch


def tiny_images(w: Path) -> None:
    make_images(w / "imgs")


def missing_checkpoint(w: Path) -> None:
    pass


def crafted_checkpoint(w: Path) -> None:
    import torch

    torch.save({"state_dict": {}, "payload": Crafted(w / "code_ran")}, w / "crafted.ckpt")


def faceless_ply(w: Path) -> None:
    (w / "points").mkdir()
    vertices = ["0 0 0", "1 0 0", "0 1 0", "0 0 1"]
    (w / "points" / "points.ply").write_text(
        "\n".join(
            [
                "ply",
                "format ascii 1.0",
                "element vertex 4",
                "property float x",
                "property float y",
                "property float z",
                "end_header",
                *vertices,
            ]
        )
        + "\n"
    )


def mask_of_other_size(w: Path) -> None:
    import json

    import tifffile

    (w / "real" / "images").mkdir(parents=True)
    (w / "real" / "masks").mkdir()
    tifffile.imwrite(w / "real" / "images" / "a.tif", np.full((770, 64), 128, np.uint8))  # 64 x 770 px
    tifffile.imwrite(w / "real" / "masks" / "a_m.tif", np.zeros((385, 32), np.uint8))  # half of it
    (w / "real" / "split.json").write_text(json.dumps({"train": ["a"], "test": []}))


def leaky_split(w: Path) -> None:
    import json

    tiny_images(w)
    (w / "split.json").write_text(json.dumps({"train": ["img0", "img1"], "test": ["img1"]}))


def fake_inception(w: Path) -> None:
    tiny_images(w)
    (w / "inception.pt").write_bytes(b"not the TF-Inception network")


def tiny_checkpoint(w: Path) -> None:
    """A tiny trained run (one step) whose best.ckpt the generate rows use."""
    tiny_images(w)
    cmd = [
        sys.executable,
        "-m",
        "drgan.train",
        f"data.dir={w / 'imgs'}",
        *TINY,
        *TINY_FAST,
        "run_name=tiny",
        "callbacks.fid.extractor={_target_:drgan.callbacks.RandomProjectionFeatures,dim:16}",
    ]
    subprocess.run(cmd, cwd=w, env=environment({}), check=True, capture_output=True, timeout=600)


def environment(extra: dict) -> dict:
    return {**os.environ, "DRGAN_DATA": str(DATA), "HYDRA_FULL_ERROR": "0", **extra}


TRAIN = ["drgan.train", "run_name=bad"]
ROWS = [
    Row(
        "startup",
        "(no error: Python and the imports every command needs)",
        "-",
        ["-c", "import drgan.train, drgan.models.gan_module, drgan.scene.scene, lightning"],
    ),
    # issue 14, "Checks come after expensive work"
    Row("spp", "renderer.spp not a valid count", "issue 14", [*TRAIN, "renderer.spp=0"]),
    Row("ckpt_path", "ckpt_path names no file", "issue 14", [*TRAIN, "ckpt_path={W}/missing.ckpt"]),
    Row("meshes", "material.meshes.dir is no folder", "issue 14", [*TRAIN, "material.meshes.dir={W}/no_meshes"]),
    Row("model", "model setting out of range (model.loss)", "issue 14", [*TRAIN, "model.loss=hinge"]),
    Row("callbacks", "callback setting out of range", "issue 14", [*TRAIN, "callbacks.fid.every_n_epochs=0"]),
    Row("init_from", "init_from names no file", "issue 14", [*TRAIN, "init_from={W}/missing.ckpt"]),
    Row("logger", "logger that cannot be built", "issue 14", [*TRAIN, "logger.mlflow._target_=drgan.NoSuchLogger"]),
    Row(
        "few_patches",
        "too few mined patches (3 small images -> 1 patch)",
        "issue 14",
        [*TRAIN, "data.dir={W}/few", *[a for a in TINY if "min_particles" not in a], "data.min_particles=2"],
        few_images,
        "after mining, before rendering",
    ),
    # issue 14, "Messages that mislead"
    Row("n_particles", "material.n_particles=abc", "issue 14", [*TRAIN, "material.n_particles=abc"]),
    Row(
        "loader_crop",
        "segment loader.crop=abc",
        "issue 14",
        ["drgan.segment", "real={DATA}/tio2_sem", "loader.crop=abc"],
    ),
    Row("segment_real", "segment on a missing folder (real=)", "issue 14", ["drgan.segment", "real={W}/nowhere"]),
    Row("segment_data", "segment on a missing folder (data=)", "issue 14", ["drgan.segment", "data={W}/nowhere"]),
    Row(
        "evaluate_data",
        "evaluate on a missing folder (data=)",
        "issue 14",
        ["drgan.evaluate", "data={W}/nowhere", "model={W}/missing.ckpt"],
    ),
    Row(
        "mask_size",
        "mask of another size than its image, default crop_rows",
        "issue 14",
        ["drgan.segment", "real={W}/real"],
        mask_of_other_size,
    ),
    Row(
        "ply_faceless",
        "PLY with 4 vertices and no faces",
        "issue 14",
        [*TRAIN, "material.meshes.dir={W}/points"],
        faceless_ply,
    ),
    # README
    Row("patch_size", "data.patch_size differs from renderer.resolution", "README", [*TRAIN, "data.patch_size=128"]),
    Row(
        "texture",
        "background texture without background patches",
        "README",
        [*TRAIN, "material.background_texture.enabled=true", "data.n_background=0"],
    ),
    Row(
        "split_leak",
        "split with a test id in the train list",
        "README",
        [*TRAIN, "data.dir={W}/imgs", "data.split={W}/split.json", *TINY],
        leaky_split,
    ),
    Row(
        "crafted_train",
        "crafted checkpoint as ckpt_path (code in the pickle)",
        "README",
        [*TRAIN, "ckpt_path={W}/crafted.ckpt"],
        crafted_checkpoint,
    ),
    Row(
        "crafted_init",
        "crafted checkpoint as init_from",
        "README",
        [*TRAIN, "init_from={W}/crafted.ckpt"],
        crafted_checkpoint,
    ),
    Row(
        "crafted_generate",
        "crafted checkpoint as generate's ckpt",
        "README",
        ["drgan.generate", "ckpt={W}/crafted.ckpt", "out={W}/gen", "n=2", "n_background=0"],
        crafted_checkpoint,
    ),
    Row(
        "crafted_evaluate",
        "crafted checkpoint as evaluate's model",
        "README",
        ["drgan.evaluate", "data={DATA}/tio2_sem", "model={W}/crafted.ckpt"],
        crafted_checkpoint,
    ),
    Row(
        "generate_material",
        "generate: checkpoint trained for another material",
        "README",
        ["drgan.generate", "ckpt={W}/runs/tio2_sem/tiny", "material=tio2_him", "out={W}/gen", "n=2"],
        tiny_checkpoint,
    ),
    Row(
        "kid_subset",
        "KID subset larger than the sample",
        "README",
        [
            *TRAIN,
            "data.dir={W}/imgs",
            *TINY,
            *TINY_FAST,
            "+callbacks.fid.kid_subset_size=1000",
            "callbacks.fid.extractor={_target_:drgan.callbacks.RandomProjectionFeatures,dim:16}",
        ],
        tiny_images,
        "before training",
    ),
    Row(
        "fid_network",
        "FID network file with another SHA-256",
        "README",
        [
            *TRAIN,
            "data.dir={W}/imgs",
            *TINY,
            *TINY_FAST,
            "callbacks.fid.extractor={_target_:drgan.metrics.inception.InceptionFeatures,weights_path:{W}/inception.pt}",
        ],
        fake_inception,
        "before training",
    ),
]


def work_done(w: Path) -> str:
    """What the command computed before it stopped, from the files it left."""
    done = []
    if list(w.glob("runs/*/bad/patches/patches.npz")):
        done.append("patches mined")
    if list(w.glob("runs/*/bad/checkpoints/*.ckpt")) or list(w.glob("runs/segment/**/checkpoints/*.ckpt")):
        done.append("trained (checkpoint written)")
    if list(w.glob("gen/images/*.png")):
        done.append("images rendered")
    if list(w.glob("runs/evaluate/**/results.csv")):
        done.append("scored")
    return ", ".join(done) or "none"


ERROR_LINE = re.compile(r"^([A-Za-z_][\w.]*(Error|Exception|Exit)\b.*|Error .*)$")


def message(stderr: str) -> str:
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    errors = [line for line in lines if ERROR_LINE.match(line) and not line.startswith("Error executing job")]
    if errors:
        return errors[-1]
    return lines[-1] if lines else "(no output)"


def run(row: Row, base: Path) -> dict:
    w = base / row.id
    w.mkdir(parents=True)
    if row.setup:
        row.setup(w)
    args = [a.replace("{W}", str(w)).replace("{DATA}", str(DATA)) for a in row.args]
    start = time.perf_counter()
    command = [sys.executable, *args] if args[0] == "-c" else [sys.executable, "-m", *args]
    result = subprocess.run(command, cwd=w, env=environment(row.env), capture_output=True, text=True, timeout=1200)
    seconds = time.perf_counter() - start
    text = message(result.stderr) if result.returncode else "(exit 0)"
    text = text.replace(str(w), "$W").replace(str(DATA), "$DRGAN_DATA")
    if (w / "code_ran").exists():
        text += "  **[the checkpoint's code ran]**"
    shown = " ".join(a.replace(str(w), "$W").replace(str(DATA), "$DRGAN_DATA") for a in args)
    return {
        "row": row,
        "command": f"python {shown}" if args[0] == "-c" else f"python -m {shown}",
        "message": text,
        "done": work_done(w),
        "seconds": seconds,
        "rc": result.returncode,
    }


def cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="comma-separated row ids")
    parser.add_argument("--keep", help="run in this folder and keep it (default: a temporary folder, removed)")
    args = parser.parse_args()
    rows = [r for r in ROWS if not args.only or r.id in args.only.split(",")]
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="drgan_bad_inputs_"))
    try:
        print("| # | case (source) | command | message | work done before the error | s |")
        print("|---|---|---|---|---|---|")
        for k, row in enumerate(rows, 1):
            r = run(row, base)
            print(
                f"| {k} `{row.id}` | {cell(row.case)} ({row.source}) | `{cell(r['command'])}` | {cell(r['message'])} | "
                f"{r['done']} | {r['seconds']:.1f} |",
                flush=True,
            )
    finally:
        if not args.keep:
            shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
