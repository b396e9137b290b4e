"""FID of fixed (not learned) TSEM appearance values under scene variants: which scene change helps (issue 15).

    python experiments/tio2_tsem/probe_scene.py NAME [HYDRA_OVERRIDE ...] [--values ckpt|middle] [--n 126]
    python experiments/tio2_tsem/probe_scene.py cube material.meshes.kind=cube
    python experiments/tio2_tsem/probe_scene.py cube_s1 material.meshes.kind=cube seed=1   # another phi bank + seeds

Results (FID 181.9 for v3's scene, 134-135 with one agglomerate per view): experiments/tio2_tsem/README.md
section 6. Those probes ran before experiment=tio2_tsem defaulted to placement.max_clusters=1: to repeat them,
add placement.max_clusters=5.

No training: a GANModule is built from `train experiment=tio2_tsem` plus the overrides, its FCN replaced by one
fixed value per learned parameter (`--values ckpt`: the medians over the phi bank of a reference checkpoint,
by default runs/tio2_tsem/tsem_transmission_v3's chosen epoch 2; `middle`: the middle of each limit). It renders
--n images exactly as the FID callback does (`render_samples`: constellation i of its phi bank, seed
FID_SEED_BASE + 100003 * seed + i, the real film texture from the reference run's patches/) and scores them
against the reference run's cached real statistics (fid_cache/, the 126 train patches). The seed override
(`seed=`) changes the phi bank and the render seeds: repeat a variant with another seed to see the spread.

Writes runs/tio2_tsem/probe_scene/NAME.json (FID, KID, values, dark-pixel fraction, particles visible) and
NAME.png (the first 8 renders; synthetic only, so it may be looked at anywhere).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from drgan.callbacks.fid import FID_SEED_BASE, render_samples
from drgan.data.patches import PatchSet
from drgan.dataset.source import checkpoint_config, load_module
from drgan.errors import ConfigError, DataError
from drgan.io import write_json, write_png
from drgan.metrics.fid import FeatureStats, InceptionFeatures, kid
from drgan.models.gan_module import GANModule

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = ROOT / "runs/tio2_tsem/tsem_transmission_v3"
OUT = ROOT / "runs/tio2_tsem/probe_scene"
DARK = 0.4  # grey below which a pixel counts as particle in the dark-pixel fraction (film ~0.82, particles < 0.22)


def reference_values(ckpt: Path) -> dict[str, float]:
    """Median learned value per parameter over the reference checkpoint's phi bank."""
    module = load_module(ckpt, checkpoint_config(ckpt))
    with torch.no_grad():
        values = module.generator.learned_values(module.phi_bank).numpy()
    return {key: float(v) for key, v in zip(module.learned_keys, np.median(values, axis=0))}


def fixed_values(module: GANModule, mode: str, ckpt: Path) -> torch.Tensor:
    """(k,) fixed values in the order of the module's learned parameters."""
    if mode == "middle":
        return torch.tensor([0.5 * (p.low + p.high) for p in module.generator.learned], dtype=torch.float32)
    values = reference_values(ckpt)
    missing = [k for k in module.learned_keys if k not in values]
    if missing:
        raise ConfigError(f"--values ckpt: {ckpt} learned {sorted(values)}, the variant learns {missing} too")
    return torch.tensor([values[k] for k in module.learned_keys], dtype=torch.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="variant name (output file stem)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides on top of experiment=tio2_tsem")
    parser.add_argument("--values", choices=("ckpt", "middle"), default="ckpt")
    parser.add_argument("--ckpt", type=Path, default=REFERENCE / "checkpoints/epochs/epoch_002.ckpt")
    parser.add_argument("--reference", type=Path, default=REFERENCE, help="run with fid_cache/ and patches/")
    parser.add_argument("--n", type=int, default=126, help="images rendered and scored (training's FID: 126)")
    args = parser.parse_args()
    if args.n < 2:
        raise ConfigError(f"--n={args.n}: expected >= 2 (a covariance needs two images)")
    caches = sorted((args.reference / "fid_cache").glob("real_*.npz"))
    if len(caches) != 1:
        raise DataError(f"--reference={args.reference}: expected one fid_cache/real_*.npz, found {len(caches)}")
    real = FeatureStats.load(caches[0])

    with initialize_config_dir(str(ROOT / "src" / "drgan" / "conf"), version_base="1.3"):
        cfg = compose("train", ["experiment=tio2_tsem", *args.overrides])
    module = GANModule.from_config(cfg, m=args.n, base_dir=str(ROOT))
    module.eval()
    patches = PatchSet.load(args.reference / "patches")
    if module.textured:
        module.use_background_texture(patches.background)
    values = fixed_values(module, args.values, args.ckpt)
    module.generator.learned_values = lambda phi: values.expand(phi.shape[0], -1)  # the FCN's output, fixed

    start = time.perf_counter()
    seed_base = FID_SEED_BASE + 100_003 * int(cfg.get("seed", 0))
    with torch.no_grad():
        images, masks = render_samples(module, args.n, seed_base, progress=True, masks=True)
    render_s = time.perf_counter() - start
    features = InceptionFeatures(batch_size=16, progress=True).features(images)
    stats = FeatureStats.from_features(np.asarray(features, dtype=np.float64))
    fid = stats.fid(real)
    kid_mean, kid_std = kid(stats.features, real.features, 100, None, seed=0)
    counts = [
        len(np.unique(module.generator.sample(module.phi_bank[i], seed=seed_base + i).labels)) - 1
        for i in range(min(args.n, 16))
    ]
    result = {
        "name": args.name,
        "overrides": args.overrides,
        "values_mode": args.values,
        "values": dict(zip(module.learned_keys, values.tolist())),
        "n": args.n,
        "fid": fid,
        "kid": kid_mean,
        "kid_std": kid_std,
        "particle_fraction": float(masks.mean()),
        "dark_fraction": float((images < DARK).mean()),
        "real_dark_fraction": float((patches.train < DARK).mean()),
        "particles_visible_first16": float(np.mean(counts)),
        "render_s": render_s,
        "total_s": time.perf_counter() - start,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / f"{args.name}.json", result)
    write_png(OUT / f"{args.name}.png", np.concatenate(list(images[:8]), axis=1))
    print(
        f"{args.name}: FID {fid:.1f} KID {kid_mean:.3f} particle fraction {result['particle_fraction']:.3f} "
        f"dark {result['dark_fraction']:.3f} (real {result['real_dark_fraction']:.3f}) "
        f"visible {result['particles_visible_first16']:.1f} "
        f"render {render_s:.0f}s total {result['total_s']:.0f}s",
        flush=True,
    )


if __name__ == "__main__":
    main()
