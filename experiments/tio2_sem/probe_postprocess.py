"""FID of a generated dataset after simple image edits: which difference to the real patches matters?

    python experiments/tio2_sem/probe_postprocess.py GENERATED_DIR PATCHSET_DIR [--stats]

GENERATED_DIR: output of `python -m drgan.generate` (images/syn_*.png with labels/); PATCHSET_DIR: the
patches folder of a training run (real train patches and background patches). Takes as many synthetic
images as real patches and prints the FID (TF-Inception, as in training) of each edit against the real
patches: denoising inside particle / stage regions (the exact labels keep edges sharp), brighter
particles, the real stage texture under the rendered particles, and the real background patches alone.
--stats: only compare content (particle area fraction, particles per patch, particle and stage grey; real
patches measured with the classical segmentation of the patch selection, synthetic ones with their labels).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage as ndi

from drgan.data.classical import segment_particles
from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats
from drgan.metrics.inception import InceptionFeatures


def region_blur(image: np.ndarray, labels: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur within the particle pixels and within the stage pixels separately."""
    out = np.zeros_like(image)
    for inside in ((labels > 0).astype(np.float32), (labels == 0).astype(np.float32)):
        out += (
            inside * ndi.gaussian_filter(image * inside, sigma) / np.maximum(ndi.gaussian_filter(inside, sigma), 1e-6)
        )
    return out


def content_stats(name: str, images: np.ndarray, labels: np.ndarray) -> None:
    def pct(values) -> str:
        return " / ".join(f"{v:.3g}" for v in np.percentile(values, [10, 50, 90]))

    counts = [len(np.unique(lab[lab > 0])) for lab in labels]
    print(
        f"| {name} | {pct([(lab > 0).mean() for lab in labels])} | {pct(counts)} | "
        f"{pct([im[lab > 0].mean() for im, lab in zip(images, labels)])} | {pct([im[lab == 0].mean() for im, lab in zip(images, labels)])} |"
    )


def main(generated: Path, patchset: Path, stats_only: bool = False) -> None:
    patches = PatchSet.load(patchset)
    real, backgrounds = patches.train, patches.background
    files = sorted((generated / "images").glob("syn_*.png"))[: len(real)]
    images = np.stack([np.asarray(Image.open(f), dtype=np.float32) / 255 for f in files])
    labels = np.stack([np.asarray(Image.open(generated / "labels" / f.name)) for f in files])
    if stats_only:
        print("10th / 50th / 90th percentiles over patches\n")
        print("| set | particle area fraction | particles | particle grey | stage grey |\n|---|---|---|---|---|")
        content_stats("real train patches", real, np.stack([segment_particles(p)[0] for p in real]))
        content_stats("synthetic", images, labels)
        return
    extractor = InceptionFeatures(batch_size=16)
    real_stats = FeatureStats.from_features(extractor.features(real))

    def fid(x: np.ndarray) -> float:
        return FeatureStats.from_features(extractor.features(np.clip(x, 0, 1))).fid(real_stats)

    stage_level = np.median(images[labels == 0])
    rng = np.random.default_rng(0)
    textured = [
        np.where(lab > 0, im, bg * (im[lab == 0].mean() / bg.mean()))
        for im, lab, bg in zip(images, labels, backgrounds[rng.integers(len(backgrounds), size=len(images))])
    ]
    edits = {
        "as generated": images,
        "denoised within regions, sigma 1 px": np.stack([region_blur(i, l, 1.0) for i, l in zip(images, labels)]),
        "denoised within regions, sigma 2 px": np.stack([region_blur(i, l, 2.0) for i, l in zip(images, labels)]),
        "denoised everywhere, sigma 1 px": ndi.gaussian_filter(images, (0, 1.0, 1.0)),
        "particle contrast x 1.6": np.where(labels > 0, stage_level + (images - stage_level) * 1.6, images),
        "particle contrast x 2.2": np.where(labels > 0, stage_level + (images - stage_level) * 2.2, images),
        "real stage texture under the particles": np.stack(textured),
        "real background patches alone": backgrounds[: len(real)],
    }
    print(f"{len(images)} synthetic images from {generated} against {len(real)} real patches\n")
    print("| edit | FID |\n|---|---|")
    for name, x in edits.items():
        print(f"| {name} | {fid(x):.1f} |", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), "--stats" in sys.argv[3:])
