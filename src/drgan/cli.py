"""`drgan STAGE [KEY=VALUE ...]`: every stage of drgan as a subcommand of one console command.

`drgan pipeline data.dir=DIR name=NAME` is `python -m drgan.pipeline data.dir=DIR name=NAME`, and so on for every
stage: the subcommand runs the stage's module as its own command would, with the same settings and files.
`drgan --help` lists the stages; `drgan STAGE --help` says what a stage does and lists its settings with their
comments (the stage's config file).
"""

from __future__ import annotations

import ast
import importlib.util
import runpy
import sys
from collections.abc import Sequence
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent

# The registry of stages, the one place a new stage is named (CONTRIBUTING.md, "a stage"): subcommand -> (module run
# as `python -m MODULE`, the config file of its settings relative to the package (or an absolute path) or None, what
# it does), in pipeline order. `drgan --help`, `drgan NAME --help` and `drgan NAME ...` read it, and
# tests/test_cli.py checks that the import contracts in pyproject.toml put every module named here in a layer.
COMMANDS = {
    "pipeline": (
        "drgan.pipeline",
        "conf/pipeline/pipeline.yaml",
        "a folder of images to particle statistics, all stages",
    ),
    "profile": ("drgan.profile", "conf/gan/profile.yaml", "read unannotated images, propose a material"),
    "train": ("drgan.train", "conf/gan/train.yaml", "train the GAN (renderer values and noise) on real patches"),
    "generate": ("drgan.generate", "conf/gan/generate.yaml", "render annotated image/mask pairs from a trained GAN"),
    "segment": ("drgan.segment", "conf/segmentation/segment.yaml", "train a segmenter on generated (or real) pairs"),
    "evaluate": ("drgan.evaluate", "conf/segmentation/evaluate.yaml", "score segmenters on annotated real images"),
    "analyze": ("drgan.analyze", "conf/segmentation/analyze.yaml", "particle sizes and counts of new images"),
    "render": ("drgan.render", "conf/gan/render.yaml", "one synthetic image and its exact annotations"),
    "realism": ("drgan.realism", "conf/gan/realism.yaml", "can a small CNN tell synthetic patches from real ones?"),
    "meshes": ("drgan.meshes", "conf/gan/meshes.yaml", "write a library of particle meshes"),
    "import-official": (
        "drgan.import_official",
        "conf/gan/import_official.yaml",
        "a generator of the official code as a run",
    ),
    "export-nnunet": (
        "drgan.export_nnunet",
        "conf/segmentation/export_nnunet.yaml",
        "a generated set in nnU-Net's layout",
    ),
    "mlflow-ui": ("drgan.mlflow_ui", None, "serve the MLflow store of your runs"),
    "view": ("drgan.view", None, "a run's images and particle outlines in napari (the napari extra)"),
}


def _docstring(module: str) -> str:
    """A module's docstring, read without importing it (the help stays instant; finding a submodule imports only
    its parent packages, and ``import drgan`` imports nothing)."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        return ""
    return ast.get_docstring(ast.parse(Path(spec.origin).read_text())) or ""


def help_text() -> str:
    width = max(len(name) for name in COMMANDS)
    lines = [
        "drgan: realistic, exactly annotated training data from unannotated microscope images of nanoparticles,",
        "and from it segmenters and particle statistics (DiffRenderGAN).",
        "",
        "usage: drgan STAGE [KEY=VALUE ...]      (the same as python -m drgan.STAGE KEY=VALUE ...)",
        "       drgan STAGE --help               what the stage does and its settings",
        "",
        "stages:",
    ]
    lines += [f"  {name:<{width}}  {what}" for name, (_, _, what) in COMMANDS.items()]
    lines += ["", "Start with: drgan pipeline data.dir=/path/to/images name=mine"]
    return "\n".join(lines)


def stage_help(name: str) -> str:
    from drgan.launch.runtime import stage_help as text

    module, config, _ = COMMANDS[name]
    where = None if config is None else (config if Path(config).is_absolute() else f"src/drgan/{config}")
    return text(f"drgan {name}", _docstring(module), None if config is None else PACKAGE / config, where or "")


def _print(text: str) -> None:
    try:
        print(text)
        sys.stdout.flush()
    except BrokenPipeError:  # `drgan --help | head`: the reader left
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        _print(help_text())
        return 0
    name, rest = argv[0], argv[1:]
    name = {"import_official": "import-official", "export_nnunet": "export-nnunet"}.get(name, name)
    if name not in COMMANDS:
        print(f"drgan: no stage {argv[0]!r}; the stages are {', '.join(COMMANDS)} (drgan --help)", file=sys.stderr)
        return 2
    if any(a in ("-h", "--help") for a in rest) and name != "mlflow-ui":
        _print(stage_help(name))
        return 0
    sys.argv = [f"drgan {name}", *rest]
    try:
        runpy.run_module(COMMANDS[name][0], run_name="__main__", alter_sys=True)
    except SystemExit as done:
        return done.code if isinstance(done.code, int) else (0 if done.code is None else 1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
