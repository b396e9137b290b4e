"""Write a mesh library folder: `python -m drgan.meshes kind=cube count=40 seed=0 out=meshes/tio2_cubes`.

Writes out/mesh_000.ply, ... (binary PLY, unit convention of drgan.scene.particle_meshes) and out/manifest.json
(kind, count, seed, effective generator parameters, per-mesh vertex and face counts).
Generator parameters: `+params.NAME=VALUE`, e.g. `+params.displacement=0.15`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from drgan.launch.runtime import stage_main, start
from drgan.scene.particle_meshes import generator_parameters, iter_meshes, save_mesh_set

log = logging.getLogger(__name__)

UNIT_CONVENTION = "centred at the bounding-box centre; largest bounding-box extent = 1 (scale = that extent)"


def write_mesh_library(kind: str, count: int, seed: int, out: str | Path, params: dict | None = None) -> Path:
    """Generate `count` meshes of `kind` and save them with a manifest into `out`; returns the manifest path."""
    parameters = generator_parameters(kind, **(params or {}))  # ConfigError for an unknown kind or parameter
    meshes = list(
        tqdm(iter_meshes(kind, count, seed, **parameters), total=count, desc=f"{kind} meshes", disable=count < 20)
    )
    manifest = {"kind": kind, "count": count, "seed": seed, "parameters": parameters, "units": UNIT_CONVENTION}
    return save_mesh_set(meshes, out, manifest)


@stage_main("conf/gan", "meshes")
def main(cfg: DictConfig) -> None:
    params = OmegaConf.to_container(cfg.params, resolve=True)
    manifest_path = write_mesh_library(cfg.kind, cfg.count, cfg.seed, Path(cfg.out), params)
    log.info("wrote %d %s meshes and %s", cfg.count, cfg.kind, manifest_path)


if __name__ == "__main__":
    start(main)
