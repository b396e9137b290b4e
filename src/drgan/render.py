"""`python -m drgan.render material=tio2_sem out=DIR`: one synthetic image and its exact annotations.

Writes DIR/image.png (8-bit grey), DIR/labels.png (instance ids, 0 = background, 16-bit when n > 255),
DIR/mask.png (0 background, 1 particle, 2 contour) and DIR/params.json (phi, parameters, sigma, seed).
The FCN is freshly initialised (seeded): the picture shows the scene, not a trained material.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from hydra.utils import get_original_cwd
from omegaconf import DictConfig, OmegaConf

from drgan.core import io
from drgan.launch.runtime import stage_main, start
from drgan.models import build
from drgan.scene.config import typed_material
from drgan.scene.labels import class_mask

log = logging.getLogger(__name__)


def render_to_folder(cfg: DictConfig, out: Path, base_dir: Path | None = None) -> dict:
    material = typed_material(cfg.material)
    generator = build.build_generator(cfg, base_dir=base_dir, seed=int(cfg.seed), material=material)
    phi = build.sample_phi(cfg, m=1, seed=int(cfg.seed), material=material)[0]
    start = time.perf_counter()
    sample = generator.sample(phi, seed=int(cfg.seed))
    seconds = time.perf_counter() - start
    mask = class_mask(sample.labels, material.contour_px)
    io.write_png(out / "image.png", sample.image)
    io.write_png(out / "labels.png", sample.labels)
    io.write_png(out / "mask.png", mask)
    record = {
        "material": cfg.material.name,
        "seed": sample.seed,
        "spp": generator.scene.spec.render.spp,
        "resolution": generator.scene.spec.render.resolution,
        "variant": generator.scene.variant,
        "render_seconds": round(seconds, 3),
        "parameters": sample.parameters,
        "phi": sample.phi.tolist(),
        "phi_columns": ["x_px", "y_px", "z_px", "scale_px"],
    }
    io.write_json(out / "params.json", record)
    return record


@stage_main("conf/gan", "render")
def main(cfg: DictConfig) -> None:
    base = Path(get_original_cwd())
    out = Path(cfg.out)
    out = out if out.is_absolute() else base / out
    record = render_to_folder(cfg, out, base_dir=base)
    log.info("wrote %s (render %.2f s, %s)", out, record["render_seconds"], OmegaConf.select(cfg, "material.name"))


if __name__ == "__main__":
    start(main)
