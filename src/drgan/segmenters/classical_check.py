"""The segmenter's sizes against the profile's classical ones on the user's own images, and which of the two drgan
trusts.

The closed-loop check (drgan.segmenters.closed_loop) measures a segmenter where the truth is exact, on generated
images, so it cannot see what the generated images lack. The profile's classical segmentation (threshold + watershed at
the measured scale; its sizes at half contrast of the images' mean edge, the boundary of ISO 13322-1 and of drgan's
masks) measures the same images without training. When the two medians disagree beyond the check's interval,
comparing the two segmentations particle by particle on the user's images says why (`outline_comparison`, pooled by
`pool`; analyze writes the pool to summary.json as ``classical``):

- **merges**: the segmenter's regions hold two or more classical particles far more often than the classical regions
  hold two of the segmenter's, and than the segmenter merged generated particles: it merges on the user's images
  touching particles it separates on generated ones, and its particles come out larger and fewer. The classical sizes
  are trusted.
- **the other way**: the classical segmentation merges what the segmenter separates; the segmenter's sizes are
  trusted.
- **outlines**: the particles both find are drawn wider (or narrower) by the segmenter than at half contrast, while on
  generated images its outlines lie at the true edge: it places the edge elsewhere on the user's images. The classical
  sizes are trusted when the profile found the images' half contrast (else both outlines are conventions).

`compare_with_classical` writes the sentence the report and statistics.md print. The measurements that set these
rules: experiments/statistics/README.md, "Which sizes to trust when the two disagree".
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drgan.errors import ConfigError

log = logging.getLogger(__name__)

EXACT = 0.05  # a closed-loop median error within this counts as exact (issue target on real images: 5 %)
AGREE = 0.05  # the classical median may differ this much beyond the closed-loop interval and still agree
MERGE_EXCESS = 0.10  # merges (shares of particles) one segmentation makes beyond the other's that explain a gap


@dataclass(frozen=True)
class ClassicalReference:
    """A drgan.profile run's classical segmentation: its label images (``labels/ID.tif``), its median diameter (at
    half contrast when it found the images' mean edge) and how far it moved the segmented outlines to get there."""

    labels: Path
    median_diameter_px: float | None
    outline_shift_px: float

    @classmethod
    def of_run(cls, folder: Path) -> ClassicalReference:
        """The profile run in ``folder``, or a ConfigError naming what is missing (before any image is read)."""
        record, labels = folder / "profile.json", folder / "labels"
        if not record.is_file():
            raise ConfigError(f"profile={folder}: expected a drgan.profile run folder (profile.json in it)")
        if not labels.is_dir():
            log.warning("profile=%s has no labels/ (a profile run older than its label images): medians only", folder)
        sizes = json.loads(record.read_text()).get("sizes") or {}
        return cls(labels, sizes.get("median_diameter_px"), float(sizes.get("outline_shift_px") or 0.0))

    def read(self, image_id: str, shape: tuple[int, int]) -> np.ndarray | None:
        """The classical instance labels of ``image_id``; None when the profile did not segment that image (it reads
        the training images only) or segmented it at another size."""
        from drgan.data.imagej import read_label_tiff

        path = self.labels / f"{image_id}.tif"
        if not path.is_file():  # (also when the run has no labels/ at all)
            return None
        labels = read_label_tiff(path)[0]
        if labels.shape != tuple(shape):
            log.warning("%s: %s px, the segmented image %s px: not compared", path, labels.shape, tuple(shape))
            return None
        return labels


def outline_comparison(segmenter: np.ndarray, classical: np.ndarray) -> dict:
    """One image's two instance segmentations against each other (drgan.metrics.instance_scores.error_sources both
    ways): particles of each, the classical particles merged by the segmenter with a neighbour, the segmenter's merged
    by the classical segmentation, and per particle both find (IoU > 0.5) the diameter difference (segmenter minus
    classical, px, at the classical segmented outlines)."""
    from drgan.metrics.instance_scores import error_sources

    ahead = error_sources(segmenter, classical)
    back = error_sources(classical, segmenter)
    return {
        "classical": ahead["n_true"],
        "segmenter": ahead["n_pred"],
        "merged_by_segmenter": ahead["merged"],
        "merged_by_classical": back["merged"],
        "diameter_differences": np.asarray(ahead["diameter_offset"], np.float64),
    }


def pool(per_image: Sequence[Mapping], reference: ClassicalReference) -> dict | None:
    """The images' `outline_comparison`s pooled (shares over all particles); the matched particles' median diameter
    difference taken against the classical outlines moved to half contrast (``outline_shift_px`` each side). Without
    a compared image only the profile's median and whether it is at half contrast."""
    base = {
        "median_diameter_px": reference.median_diameter_px,
        "half_contrast": reference.outline_shift_px != 0.0,
        "images": len(per_image),
    }
    if not per_image:
        return base
    n_classical = sum(c["classical"] for c in per_image)
    n_segmenter = sum(c["segmenter"] for c in per_image)
    differences = np.concatenate([c["diameter_differences"] for c in per_image])
    return base | {
        "classical_particles": n_classical,
        "segmenter_particles": n_segmenter,
        "merged_by_segmenter": sum(c["merged_by_segmenter"] for c in per_image) / max(n_classical, 1),
        "merged_by_classical": sum(c["merged_by_classical"] for c in per_image) / max(n_segmenter, 1),
        "matched": int(differences.size),
        "matched_difference_px": (
            float(np.median(differences)) - 2.0 * reference.outline_shift_px if differences.size else None
        ),
    }


def _percent(value: float) -> str:
    return f"{100 * value:+.1f} %"


def _share(value: float) -> str:
    return f"{100 * value:.0f} %"


def _interval(cell: Mapping) -> tuple[float, float]:
    value = cell["value"]
    low = cell["low"] if cell.get("low") is not None else value
    high = cell["high"] if cell.get("high") is not None else value
    return low, high


def _cause(gap: float, classical_px: float, check: Mapping | None, outlines: Mapping | None) -> str | None:
    """Why the two medians disagree, read from the two segmentations of the user's images, and which is trusted; None
    when they agree within ``AGREE`` or the comparison says nothing decisive."""
    if not outlines or not outlines.get("images") or abs(gap) <= AGREE:
        return None
    by_segmenter, by_classical = outlines["merged_by_segmenter"], outlines["merged_by_classical"]
    generated = (check or {}).get("merged")
    n = outlines["images"]
    if gap > 0 and by_segmenter >= by_classical + MERGE_EXCESS and by_segmenter >= (generated or 0.0) + MERGE_EXCESS:
        unseen = (
            f"; the segmenter merged {_share(generated)} of the generated particles of its check): it merges touching "
            "particles on your images that its check did not see merged"
            if generated is not None
            else "): it merges touching particles that the classical segmentation separates"
        )
        return (
            f". On your {n} images the segmenter holds {_share(by_segmenter)} of the classical particles in one region "
            f"with a neighbour (the classical segmentation {_share(by_classical)} of the segmenter's{unseen}, so its "
            "particles come out larger and fewer. drgan trusts the classical sizes more; the segmenter's count is low "
            "too. The classical segmentation merges touching particles as well: count a few by hand, or score a few "
            "annotated images (annotated=), before publishing the count."
        )
    if gap < 0 and by_classical >= by_segmenter + MERGE_EXCESS:
        return (
            f". On your {n} images the classical segmentation holds {_share(by_classical)} of the segmenter's particles "
            f"in one region with a neighbour (the segmenter {_share(by_segmenter)} of the classical ones): the "
            "classical sizes are merges. drgan trusts the segmenter's sizes."
        )
    difference = outlines.get("matched_difference_px")
    if difference is None or not outlines.get("half_contrast"):
        return None
    edge = (check or {}).get("edge_offset_px")
    unexplained = difference - 2.0 * (edge or 0.0)  # what the segmenter's own edge offset does not account for
    if unexplained * gap > 0 and abs(unexplained) / classical_px >= AGREE:
        where = (
            f" (on generated images its outlines lie {edge:+.2f} px from the true edge: it draws the edge elsewhere on "
            "your images)"
            if edge is not None
            else ""
        )
        return (
            f". The {outlines['matched']} particles both find are {difference:+.1f} px in diameter from the classical "
            f"outlines at half contrast of your images' mean edge{where}. drgan trusts the classical sizes (half "
            "contrast: the boundary of ISO 13322-1 and of drgan's masks)."
        )
    return None


def _why_biased(check: Mapping) -> str:
    """Where a biased check's error comes from: merged particles or outlines off the true edge."""
    merged, edge = check.get("merged"), check.get("edge_offset_px")
    if merged is not None and merged >= MERGE_EXCESS / 2:
        return f" ({100 * merged:.1f} % of the generated particles merged with a neighbour)"
    if edge is not None and abs(edge) >= 0.5:
        return f" (its outlines {edge:+.2f} px from the true edge)"
    return ""


def compare_with_classical(
    median_px: float | None, classical_px: float | None, check: Mapping | None, outlines: Mapping | None = None
) -> str:
    """The sentence on the segmenter's median diameter against the profile's classical one (threshold + watershed on
    the same images, no training): whether they agree within the closed-loop interval (widened by ``AGREE``), and
    where they do not, why (``outlines``: `pool`'s comparison of the two segmentations, when measured) and which one
    drgan trusts."""
    if not median_px or not classical_px:
        return "No comparison with the profile's classical sizes (one of the two medians is missing)."
    gap = median_px / classical_px - 1.0
    said = (
        f"The segmenter's median diameter ({median_px:.1f} px) is {100 * gap:+.1f} % from the profile's classical one "
        f"({classical_px:.1f} px; threshold + watershed, no training)"
    )
    value = (check or {}).get("median_error", {}).get("value")
    if value is not None:
        low, high = _interval(check["median_error"])
        if low - AGREE <= gap <= high + AGREE:
            if abs(value) <= EXACT:
                return (
                    said + ": the two agree, and the segmenter is exact on generated images. drgan trusts these sizes."
                )
            return (
                said + f": the gap is what the closed-loop check predicts (the segmenter measures {_percent(value)} on "
                "generated images with exact outlines). drgan trusts the classical sizes more: the segmenter's "
                "sizes carry its own measured error" + _why_biased(check) + "."
            )
        if abs(gap) <= AGREE:  # a biased check, yet the two methods agree on the user's images
            merged = check.get("merged")
            how = f" ({100 * merged:.1f} % of their particles merged)" if merged is not None else ""
            return (
                said + f": the two agree within {100 * AGREE:.0f} %, though on generated images the segmenter measures "
                f"{_percent(value)}{how}. Two independent methods agree on your images, so the generated scenes are "
                "harder to measure than yours (their touching particles show no neck the segmenter can cut, e.g. "
                "particles piled over each other) and drgan trusts these sizes; score a few annotated images "
                "(annotated=) to be sure."
            )
        said += f", beyond the closed-loop interval [{_percent(low)}, {_percent(high)}] widened by {100 * AGREE:.0f} %"
    cause = _cause(gap, classical_px, check, outlines)
    if cause:
        return said + cause
    if value is None:
        if abs(gap) <= AGREE:
            return said + f": the two agree within {100 * AGREE:.0f} % (the segmenter has no closed-loop check)."
        return said + "; without a closed-loop check neither can be preferred: look at both overlays."
    if abs(value) <= EXACT:
        return (
            said + ": the segmenter is exact on generated images, so the gap is either the classical segmentation's "
            "own error (merges, fringes, specks) or a difference between your images and the generated ones at the "
            "particles' edges. drgan trusts the segmenter's sizes (its error is measured, the classical one's is "
            "not); compare the two overlays before publishing."
        )
    return (
        said + f": the segmenter is itself biased ({_percent(value)} on generated images) and disagrees with the "
        "classical sizes by more than that. Neither is trusted: compare the two overlays, or score both on a few "
        "annotated images (annotated=)."
    )
