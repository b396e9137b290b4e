"""FID of a scene at fixed (not learned) values: which scene change helps, before any training (issues 15, 17).

    python experiments/tio2_tsem/probe_scene.py NAME [HYDRA_OVERRIDE ...] [--experiment tio2_tsem] [--reference RUN]
                                               [--values ckpt|middle] [--ckpt CKPT] [--set KEY=VALUE ...] [--n N]
    python experiments/tio2_tsem/probe_scene.py cube material.meshes.kind=cube              # TSEM, v3's values
    python experiments/tio2_tsem/probe_scene.py cube_s1 material.meshes.kind=cube seed=1    # another phi bank + seeds
    python experiments/tio2_tsem/probe_scene.py counts_8_32 --experiment tio2_sem --reference runs/tio2_sem/RUN \
        --values ckpt --ckpt runs/tio2_sem/RUN/checkpoints/best.ckpt material.n_particles_min=8 renderer.spp=121

The one harness for the scene probes (it replaces the SEM scripts probe_appearance.py and probe_counts.py, which
copied it; experiments/tio2_sem/README.md says which commit holds them as they ran). A GANModule is built from
`train experiment=EXPERIMENT` plus the overrides, and every learned parameter is fixed for every image with the
package's own `drgan.synthetic.source.use_parameters` (what `drgan.generate parameters=` does): `--values ckpt`, the
medians over a checkpoint's phi bank (default for TSEM: runs/tio2_tsem/tsem_transmission_v3's epoch 2); `middle`,
the middle of each limit; `--set KEY=VALUE` (repeatable, e.g. `--set particle.roughness=0.5`) replaces single
values. It renders --n images exactly as the FID callback does (`render_samples`: constellation i of its phi bank,
seed FID_SEED_BASE + 100003 * seed + i; the real background texture from the reference run's patches/) and scores
them against the reference run's real train patches (its fid_cache/ when it holds one, else their Inception
features). `seed=` changes the phi bank and the render seeds: repeat a variant with another seed to see the spread.

Writes OUT/NAME.json (FID, KID, values, dark-pixel fraction, particles visible) and NAME.png (the first 8 renders:
synthetic only, so it may be looked at anywhere); OUT defaults to runs/probe_scene/EXPERIMENT.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from drgan.callbacks.fid import FID_SEED_BASE, render_samples
from drgan.core.errors import ConfigError, DataError
from drgan.core.io import write_json, write_png
from drgan.data.patches import PatchSet
from drgan.launch.configs import compose
from drgan.metrics.feature_distances import FeatureStats, kid
from drgan.metrics.inception import InceptionFeatures
from drgan.models.gan_module import GANModule
from drgan.synthetic.source import checkpoint_config, load_module, use_parameters

ROOT = Path(__file__).resolve().parents[2]
TSEM_REFERENCE = ROOT / "runs/tio2_tsem/tsem_transmission_v3"
DARK = 0.4  # grey below which a pixel counts as dark (TSEM: film ~0.82, particles < 0.22)


def checkpoint_medians(ckpt: Path) -> dict[str, float]:
    """Median learned value per parameter over a checkpoint's phi bank."""
    module = load_module(ckpt, checkpoint_config(ckpt))
    with torch.no_grad():
        values = module.generator.learned_values(module.phi_bank).numpy()
    return {key: float(v) for key, v in zip(module.learned_keys, np.median(values, axis=0))}


def probe_values(module: GANModule, mode: str, ckpt: Path | None, given: list[str]) -> dict[str, float] | str:
    """The values for `use_parameters`: "middle", or a mapping key -> value (checkpoint medians and --set)."""
    settings = {}
    for item in given:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. particle.roughness=0.5")
        settings[key.strip()] = float(value)
    if mode == "middle" and not settings:
        return "middle"
    values = {p.key: 0.5 * (p.low + p.high) for p in module.generator.learned}
    if mode == "ckpt":
        if ckpt is None:
            raise ConfigError("--values ckpt: give --ckpt (a drgan.train checkpoint)")
        medians = checkpoint_medians(ckpt)
        missing = [k for k in values if k not in medians]
        if missing:
            raise ConfigError(f"--values ckpt: {ckpt} learned {sorted(medians)}, the variant learns {missing} too")
        values = {k: medians[k] for k in values}
    return {**values, **settings}  # use_parameters names unknown keys and values outside the limits


def real_statistics(reference: Path, patches: PatchSet) -> FeatureStats:
    caches = sorted((reference / "fid_cache").glob("real_*.npz"))
    if len(caches) > 1:
        raise DataError(f"--reference={reference}: expected at most one fid_cache/real_*.npz, found {len(caches)}")
    if caches:
        return FeatureStats.load(caches[0])
    features = InceptionFeatures(batch_size=16, progress=True).features(patches.train)
    return FeatureStats.from_features(np.asarray(features, dtype=np.float64))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="variant name (output file stem)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides on top of experiment=EXPERIMENT")
    parser.add_argument("--experiment", default="tio2_tsem", help="train config's experiment (default tio2_tsem)")
    parser.add_argument("--reference", type=Path, help="training run with patches/ (and fid_cache/)")
    parser.add_argument("--values", choices=("ckpt", "middle"), default="ckpt")
    parser.add_argument("--ckpt", type=Path, help="checkpoint whose phi-bank medians --values ckpt takes")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="one learned value")
    parser.add_argument("--n", type=int, help="images rendered and scored (default: as many as real patches)")
    parser.add_argument("--out", type=Path, help="output folder (default runs/probe_scene/EXPERIMENT)")
    args = parser.parse_intermixed_args()  # overrides may follow the options
    if args.experiment == "tio2_tsem":
        args.reference = args.reference or TSEM_REFERENCE
        args.ckpt = args.ckpt or TSEM_REFERENCE / "checkpoints/epochs/epoch_002.ckpt"
    if args.reference is None:
        raise ConfigError(f"--experiment {args.experiment}: give --reference (a training run with patches/)")
    patches = PatchSet.load(args.reference / "patches")
    n = args.n if args.n is not None else len(patches.train)
    if n < 2:
        raise ConfigError(f"--n={n}: expected >= 2 (a covariance needs two images)")
    real = real_statistics(args.reference, patches)

    cfg = compose([f"experiment={args.experiment}", *args.overrides], config_name="train")
    module = GANModule.from_config(cfg, m=n, base_dir=str(ROOT))
    module.eval()
    if module.textured:
        module.use_background_texture(patches.background)
    values = probe_values(module, args.values, args.ckpt, args.set)
    use_parameters(module, values, {})

    start = time.perf_counter()
    seed_base = FID_SEED_BASE + 100_003 * int(cfg.get("seed", 0))
    with torch.no_grad():
        images, masks = render_samples(module, n, seed_base, progress=True, masks=True)
    render_s = time.perf_counter() - start
    features = InceptionFeatures(batch_size=16, progress=True).features(images)
    stats = FeatureStats.from_features(np.asarray(features, dtype=np.float64))
    fid = stats.fid(real)
    kid_mean, kid_std = kid(stats.features, real.features, 100, None, seed=0)
    counts = [
        len(np.unique(module.generator.sample(module.phi_bank[i], seed=seed_base + i).labels)) - 1
        for i in range(min(n, 16))
    ]
    result = {
        "name": args.name,
        "experiment": args.experiment,
        "overrides": args.overrides,
        "values_mode": args.values,
        "values": dict(zip(module.learned_keys, module.generator.fixed_values.tolist())),
        "n": n,
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
    out = args.out or ROOT / "runs/probe_scene" / args.experiment
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{args.name}.json", result)
    write_png(out / f"{args.name}.png", np.concatenate(list(images[:8]), axis=1))
    print(
        f"{args.name}: FID {fid:.1f} KID {kid_mean:.3f} particle fraction {result['particle_fraction']:.3f} "
        f"dark {result['dark_fraction']:.3f} (real {result['real_dark_fraction']:.3f}) "
        f"visible {result['particles_visible_first16']:.1f} render {render_s:.0f}s total {result['total_s']:.0f}s",
        flush=True,
    )


if __name__ == "__main__":
    main()
