"""Compose drgan's Hydra configs from Python (benchmarks, notebooks, tests) without a ``@hydra.main`` entry point.

    from drgan.configs import compose
    cfg = compose(["material=tio2_sem", "renderer.spp=16"], config_name="train")

The entry points read their configs from the package, so an installed drgan works from any folder. Two roots, one
per family of entry points, so that a key of one family never meets a group of the other (``data=DIR`` is a folder
for drgan.segment but a config group for drgan.train):

- ``drgan/conf/gan/``: train, generate, render, profile, realism, meshes (groups: material, renderer, model, ...);
- ``drgan/conf/segmentation/``: segment, evaluate, analyze, export_nnunet;
- ``drgan/conf/common/``: the groups both use (paths, logger), on their search path as ``pkg://drgan.conf.common``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from drgan.errors import ConfigError

CONF_DIR = Path(__file__).resolve().parent / "conf"
ROOTS = ("gan", "segmentation")


def conf_dir(root: str = "gan") -> Path:
    """The config root ``root`` (one of `ROOTS`); a clear error when the package was installed without its configs."""
    if root not in ROOTS:
        raise ConfigError(f"config root {root!r}: expected one of {ROOTS}")
    folder = CONF_DIR / root
    if not any(folder.glob("*.yaml")):
        raise ConfigError(
            f"drgan's config folder {folder} has no configs: the package was installed without them "
            "(reinstall it: `pip install .` from a checkout includes drgan/conf)"
        )
    return folder


def config_root(config_name: str) -> Path:
    """The root that holds the primary config ``config_name`` (e.g. "train", "segment")."""
    for root in ROOTS:
        if (conf_dir(root) / f"{config_name}.yaml").is_file():
            return conf_dir(root)
    names = sorted(p.stem for root in ROOTS for p in conf_dir(root).glob("*.yaml"))
    raise ConfigError(f"config_name={config_name!r}: expected one of {names}")


def compose(overrides: Sequence[str] = (), config_name: str = "render"):
    """The composed config ``config_name`` (e.g. "render", "train", "segment") with Hydra ``overrides`` applied."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    import drgan  # noqa: F401  (registers the config resolvers)

    if isinstance(overrides, str):
        raise ConfigError(f"overrides={overrides!r}: expected a list of strings such as ['renderer.spp=16']")
    with initialize_config_dir(version_base="1.3", config_dir=str(config_root(config_name))):
        return hydra_compose(config_name=config_name, overrides=list(overrides))
