"""Compose drgan's Hydra configs from Python (benchmarks, notebooks, tests) without a ``@hydra.main`` entry point.

    from drgan.configs import compose
    cfg = compose(["material=tio2_sem", "renderer.spp=16"], config_name="train")

The entry points (`drgan.train`, `drgan.render`, ...) read the same folder: ``drgan/conf/``, inside the package
(Hydra's ``config_path="conf"``), so an installed drgan works from any folder.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from drgan.errors import ConfigError

CONF_DIR = Path(__file__).resolve().parent / "conf"


def conf_dir() -> Path:
    """The folder of drgan's configs; a clear error when the package was installed without the repository."""
    if not (CONF_DIR / "train.yaml").is_file():
        raise ConfigError(
            f"drgan's config folder {CONF_DIR} has no train.yaml: the package was installed without its configs "
            "(reinstall it: `pip install .` from a checkout includes drgan/conf)"
        )
    return CONF_DIR


def compose(overrides: Sequence[str] = (), config_name: str = "render"):
    """The composed config ``config_name`` (e.g. "render", "train") with Hydra ``overrides`` applied."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    import drgan  # noqa: F401  (registers the config resolvers)

    if isinstance(overrides, str):
        raise ConfigError(f"overrides={overrides!r}: expected a list of strings such as ['renderer.spp=16']")
    with initialize_config_dir(version_base="1.3", config_dir=str(conf_dir())):
        return hydra_compose(config_name=config_name, overrides=list(overrides))
