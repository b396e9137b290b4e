"""Images of the imported official generators (drgan.generate) against the official code's own (../shared/official).

    PYTHONPATH=src python experiments/official_import/compare.py --official ../shared/official --runs RUNS \
        --out experiments/official_import

RUNS/gen_<tag> are drgan datasets (images/, labels/, masks/, meta/) generated from RUNS/<tag> (the imported run).
Per case: mean grey of particle and background pixels (pooled over the set, 0-255), particle area fraction (per
image, averaged), median equivalent diameter of the particles (connected parts of mask class 1, over the set), each
as drgan / official - 1 with its standard error (bootstrap over the images of both sets); FID and KID (TF-Inception
pool3) between the sets, beside the references' even- against odd-numbered halves (the floor) and drgan's first 32
against the odd half (FID at the floor's sample size). Masks: the official masks mark a 1 px contour *outside* each
particle (class 2), cut touching particles apart with a skeletonised boundary and drop parts under 50 px; drgan's
(contour_px 1) mark the rim *inside*. So drgan's masks are compared in the official convention, made here from its
exact instance labels (`official_mask`); its own masks are reported beside them. Writes results.json, results.md and
figure.jpg (three images per case, drgan left, official right).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage
from skimage import measure
from skimage.morphology import skeletonize
from skimage.segmentation import find_boundaries

TAGS = {
    "Mill2021TiO2_paper": "TiO2 HIM",
    "Mill2021SiO2_paper": "SiO2 HIM",
    "Ruehle2021TiO2_paper": "TiO2 SEM",
    "Ag_paper": "AgNW SEM",
}
TOLERANCE = {"particle_grey": 0.05, "background_grey": 0.05, "area_fraction": 0.10, "median_diameter": 0.10}
MIN_PART_PX = 50  # the official test_gan.py's --min_mask_size
PAD = 12  # the official post-processing pads by 12 px so that border particles get a closed boundary


def official_mask(labels: np.ndarray) -> np.ndarray:
    """The official masks' convention (test_gan.py's post-processing) from instance labels: background 0, particle 1,
    contour 2 = the 1 px ring outside each particle; touching particles are cut apart along a skeletonised boundary
    (closed against diagonal leaks) and parts under 50 px are dropped."""
    labels = np.pad(labels, PAD)
    between = skeletonize(find_boundaries(labels, connectivity=2, mode="outer"))
    # A diagonal step in the cut would let 8-connected parts leak through it: fill the corner.
    pattern1, pattern2 = np.array([[0, 1, 0], [0, 0, 1], [0, 0, 0]]), np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0]])
    cut = between.astype(int)
    between = between | (ndimage.correlate(cut, pattern1) == 2) | (ndimage.correlate(cut, pattern2) == 2)
    particle = (labels > 0) & ~between
    parts = measure.label(particle, connectivity=2)
    sizes = np.bincount(parts.ravel())
    particle &= sizes[parts] >= MIN_PART_PX
    mask = particle.astype(np.uint8)
    mask[find_boundaries(particle.astype(np.uint8), connectivity=2, mode="outer")] = 2
    return mask[PAD:-PAD, PAD:-PAD]


def passes_official_filter(image: np.ndarray, labels: np.ndarray) -> bool:
    """test_gan.py's filter as the official masks would see this image: its shape-index mask counts a pixel as
    particle from a small partial coverage on (about one pixel wider than the exact labels), and it keeps an
    image with >= 15 % background whose particles are >= 1.15 x brighter than the background."""
    particle = ndimage.binary_dilation(labels > 0, structure=np.ones((3, 3), bool))
    if (~particle).mean() < 0.15:
        return False
    return image[particle].mean() >= 1.15 * image[~particle].mean()


def image_record(image: np.ndarray, mask: np.ndarray) -> dict:
    """What the statistics need of one image (grey 0-255, mask 0/1/2)."""
    particle = mask > 0
    parts = measure.label(mask == 1, connectivity=2)
    areas = np.bincount(parts.ravel())[1:]
    return {
        "fg_sum": float(image[particle].sum()),
        "fg_n": int(particle.sum()),
        "bg_sum": float(image[~particle].sum()),
        "bg_n": int((~particle).sum()),
        "area": float(particle.mean()),
        "diameters": np.sqrt(4 * areas[areas > 0] / np.pi),
    }


def statistics(records: list[dict]) -> dict:
    return {
        "particle_grey": sum(r["fg_sum"] for r in records) / max(1, sum(r["fg_n"] for r in records)),
        "background_grey": sum(r["bg_sum"] for r in records) / max(1, sum(r["bg_n"] for r in records)),
        "area_fraction": float(np.mean([r["area"] for r in records])),
        "median_diameter": float(np.median(np.concatenate([r["diameters"] for r in records]))),
        "particles_per_image": float(np.mean([len(r["diameters"]) for r in records])),
    }


def compare(ours: list[dict], theirs: list[dict], rounds: int = 2000, seed: int = 0) -> dict:
    """drgan / official - 1 per statistic, with its bootstrap standard error (images resampled in both sets)."""
    rng = np.random.default_rng(seed)
    a, b = statistics(ours), statistics(theirs)
    draws = {key: [] for key in TOLERANCE}
    for _ in range(rounds):
        sa = statistics([ours[i] for i in rng.integers(len(ours), size=len(ours))])
        sb = statistics([theirs[i] for i in rng.integers(len(theirs), size=len(theirs))])
        for key in TOLERANCE:
            draws[key].append(sa[key] / sb[key] - 1)
    result = {}
    for key, tolerance in TOLERANCE.items():
        diff, se = a[key] / b[key] - 1, float(np.std(draws[key]))
        # Beyond the tolerance, a difference still counts as a match while it is within two standard errors of 0.
        result[key] = {
            "drgan": a[key], "official": b[key], "diff": diff, "se": se, "tolerance": tolerance,
            "match": bool(abs(diff) <= tolerance or abs(diff) <= 2 * se),
        }  # fmt: skip
    result["particles_per_image"] = {"drgan": a["particles_per_image"], "official": b["particles_per_image"]}
    return result


def read_reference(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    names = sorted((folder / "imgs").glob("*.tif"), key=lambda p: int(p.stem))
    images = [np.asarray(Image.open(p), dtype=np.float64) for p in names]
    masks = [np.asarray(Image.open(folder / "masks" / p.name)) for p in names]
    return images, masks


def read_drgan(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Images, drgan's masks and instance labels of every finished item (meta/ID.json written last)."""
    manifest = folder / "manifest.json"
    if manifest.is_file():  # the dataset: its first n kept items (shards may have kept a few more)
        items = [e["id"] for e in json.loads(manifest.read_text())["entries"] if e["kind"] == "synthetic"]
    else:  # a dataset still being generated: every finished item
        items = sorted(p.stem for p in (folder / "meta").glob("syn_*.json"))
    images = [np.asarray(Image.open(folder / "images" / f"{i}.png"), dtype=np.float64) for i in items]
    masks = [np.asarray(Image.open(folder / "masks" / f"{i}.png")) for i in items]
    labels = [np.asarray(Image.open(folder / "labels" / f"{i}.png")).astype(np.int32) for i in items]
    return images, masks, labels


def inception_scores(ours: list[np.ndarray], theirs: list[np.ndarray], extractor) -> dict:
    from drgan.metrics.feature_distances import FeatureStats, kid

    fa = extractor.features(np.stack(ours) / 255.0)
    fb = extractor.features(np.stack(theirs) / 255.0)
    even, odd = fb[0::2], fb[1::2]

    def fid(x, y):
        return FeatureStats.from_features(x).fid(FeatureStats.from_features(y))

    return {
        "fid": fid(fa, fb),
        "kid": kid(fa, fb, seed=0)[0],
        "fid_floor_halves": fid(even, odd),
        "kid_floor_halves": kid(even, odd, seed=0)[0],
        "fid_drgan32_vs_odd": fid(fa[:32], odd),
        "kid_drgan32_vs_odd": kid(fa[:32], odd, seed=0)[0],
    }


def figure(panels: dict, path: Path, size: int = 128) -> None:
    """Rows: cases; three drgan images, then three official ones (thumbnails of ``size`` px)."""
    rows = []
    for ours, theirs in panels.values():
        tiles = [
            np.asarray(Image.fromarray(im.astype(np.uint8)).resize((size, size), Image.LANCZOS))
            for im in ours[:3] + theirs[:3]
        ]
        gap = np.full((size, 6), 255, np.uint8)
        rows.append(np.hstack([*tiles[:3], gap, *tiles[3:]]))
    Image.fromarray(np.vstack(rows)).save(path, quality=85, optimize=True)


def table(results: dict) -> str:
    lines = [
        "| case | n drgan / official | particle grey | background grey | area fraction | median diameter (px) | particles per image | FID (floor) | FID 32 vs 32 (floor) | KID x 1e3 (floor) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for tag, r in results.items():
        cells = []
        for key in TOLERANCE:
            c = r["official_masks"][key]
            mark = "" if c["match"] else " **(no)**"
            cells.append(
                f"{c['drgan']:.3g} / {c['official']:.3g} ({100 * c['diff']:+.1f} % +- {100 * c['se']:.1f}){mark}"
            )
        p = r["official_masks"]["particles_per_image"]
        s = r["inception"]
        lines.append(
            f"| {TAGS[tag]} | {r['n_drgan']} / {r['n_official']} | " + " | ".join(cells)
            + f" | {p['drgan']:.1f} / {p['official']:.1f} | {s['fid']:.1f} ({s['fid_floor_halves']:.1f}) | "
            f"{s['fid_drgan32_vs_odd']:.1f} ({s['fid_floor_halves']:.1f}) | {1e3 * s['kid']:.1f} ({1e3 * s['kid_floor_halves']:.1f}) |"
        )  # fmt: skip
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--official", type=Path, required=True, help="the shared official folder")
    parser.add_argument(
        "--runs", type=Path, required=True, help="folder of <tag>/ (imported) and gen_<tag>/ (datasets)"
    )
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--tags", nargs="*", default=list(TAGS))
    parser.add_argument("--no-inception", action="store_true", help="skip FID/KID")
    parser.add_argument("--fid-images", type=int, default=100, help="drgan images (the first) in FID/KID: CPU time")
    args = parser.parse_args()
    extractor = None
    if not args.no_inception:
        from drgan.metrics.inception import InceptionFeatures

        extractor = InceptionFeatures()
    results, panels = {}, {}
    for tag in args.tags:
        ref_images, ref_masks = read_reference(args.official / "reference" / tag)
        images, masks, labels = read_drgan(args.runs / f"gen_{tag}")
        if not images:
            print(f"{tag}: no drgan images yet")
            continue
        theirs = [image_record(i, m) for i, m in zip(ref_images, ref_masks)]
        ours = [image_record(i, official_mask(lab)) for i, lab in zip(images, labels)]
        own = [image_record(i, m) for i, m in zip(images, masks)]
        kept = [r for r, i, lab in zip(ours, images, labels) if passes_official_filter(i, lab)]
        manifest = args.runs / f"gen_{tag}" / "manifest.json"
        results[tag] = {
            "n_drgan": len(images),
            "n_official": len(ref_images),
            "official_masks": compare(ours, theirs),
            "drgan_masks": compare(own, theirs, rounds=200),
            # drgan's images that the official filter would also keep (its masks are wider than drgan's labels)
            "official_filter": {"n": len(kept), **compare(kept, theirs, rounds=500)},
            "generation": json.loads(manifest.read_text()).get("counts") if manifest.is_file() else None,
        }
        if extractor is not None:
            results[tag]["inception"] = {
                "n_drgan": min(len(images), args.fid_images),
                **inception_scores(images[: args.fid_images], ref_images, extractor),
            }
        panels[tag] = (images, ref_images)
        print(tag, json.dumps(results[tag]["official_masks"], indent=None, default=float)[:400])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    if extractor is not None:
        (args.out / "results.md").write_text(table(results))
    figure(panels, args.out / "figure.jpg")


if __name__ == "__main__":
    main()
