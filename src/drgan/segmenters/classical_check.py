"""The segmenter's sizes against the profile's classical ones on the user's own images, and which of the two drgan
trusts.

The closed-loop check (drgan.segmenters.closed_loop) measures a segmenter where the truth is exact, on generated
images, so it cannot see what the generated images lack. The profile's classical segmentation (threshold + watershed at
the measured scale; its sizes at half contrast of the images' mean edge, the boundary of ISO 13322-1 and of drgan's
masks) measures the same images without training. Two medians within 5 % agree; where they differ more, comparing the two
segmentations particle by particle on the user's images says why (`outline_comparison`, pooled by `pool`; analyze
writes the pool to summary.json as ``classical``), before the check's interval is consulted:

- **merges**: the segmenter's regions hold two or more classical particles far more often than the classical regions
  hold two of the segmenter's, and than the segmenter merged generated particles: it merges on the user's images
  touching particles it separates on generated ones, and its particles come out larger and fewer. The classical sizes
  are trusted, where the segmenter does find fewer particles (else the classical segmentation misses particles
  outright and the merges explain nothing).
- **the other way**: the classical segmentation merges what the segmenter separates, and finds fewer particles; the
  segmenter's sizes are trusted.
- **outlines**: the particles both find are drawn wider (or narrower) by the segmenter than at half contrast, while on
  generated images its outlines lie at the true edge: it places the edge elsewhere on the user's images. The classical
  sizes are trusted when the profile found the images' half contrast (else both outlines are conventions).

`judge` gives the sentence the report and statistics.md print and whose sizes drgan trusts; analyze then sizes the
classical particles too (`ClassicalReference.particles`, at half contrast) and puts the trusted sizes first. The
measurements that set these rules: experiments/statistics/trust.md, "Which sizes to trust when the two disagree".
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from drgan.core.errors import ConfigError

log = logging.getLogger(__name__)

EXACT = 0.05  # a closed-loop median error within this counts as exact (the size target on real images: 5 %)
AGREE = 0.05  # the classical median may differ this much beyond the closed-loop interval and still agree
MERGE_EXCESS = 0.10  # merges (shares of particles) one segmentation makes beyond the other's that explain a gap
SEGMENTER, CLASSICAL, BOTH = "segmenter", "classical", "both"  # whose sizes drgan trusts (Verdict.trusted)


@dataclass(frozen=True)
class Verdict:
    """`judge`'s answer: the sentence, and whose sizes drgan trusts: SEGMENTER, CLASSICAL, BOTH (the two agree) or
    None (no comparison, or neither can be preferred)."""

    sentence: str
    trusted: str | None


@dataclass(frozen=True)
class ClassicalReference:
    """A drgan.profile run's classical segmentation: its label images (``labels/ID.tif``), its median diameter (at
    half contrast when it found the images' mean edge), how far it moved the segmented outlines to get there, and the
    settings it segmented with (resolved parameters and polarity), so that any image of the same kind is segmented the
    same way."""

    labels: Path
    median_diameter_px: float | None
    outline_shift_px: float
    params: Mapping | None = None  # drgan.data.classical.SegmentParams as the profile resolved them (its scale search)
    polarity: str | None = None

    @classmethod
    def of_run(cls, folder: Path) -> ClassicalReference:
        """The profile run in ``folder``, or a ConfigError naming what is missing (before any image is read)."""
        record, labels = folder / "profile.json", folder / "labels"
        if not record.is_file():
            raise ConfigError(f"profile={folder}: expected a drgan.profile run folder (profile.json in it)")
        if not labels.is_dir():
            log.warning("profile=%s has no labels/ (a profile run older than its label images): medians only", folder)
        run = json.loads(record.read_text())
        sizes = run.get("sizes") or {}
        params = (run.get("segmentation") or {}).get("params")
        found = run.get("polarity") or {}
        polarity = found.get("value") or found.get("polarity")  # used (value), else as detected (older records)
        return cls(
            labels,
            sizes.get("median_diameter_px"),
            float(sizes.get("outline_shift_px") or 0.0),
            params if params and polarity else None,
            polarity if params else None,
        )

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

    def labels_of(self, image_id: str, image: np.ndarray) -> np.ndarray | None:
        """The classical instance labels of an image: the profile's own (`read`) where it segmented the image, else
        the image segmented now with the profile's settings (the same labels where both exist; ~2 s for 1024 x 712
        px); None for an image the profile segmented at another size, or a profile run without its settings."""
        if (self.labels / f"{image_id}.tif").is_file() or not self.params:
            return self.read(image_id, image.shape)
        from drgan.data.classical import SegmentParams
        from drgan.data.measurements import segment_image

        return segment_image(image, SegmentParams.from_config(dict(self.params)), self.polarity).labels

    def particles(self, labels: np.ndarray, min_area_px: float):
        """One image's classical particles as analyze counts its own (components under ``min_area_px`` at the
        segmented outline are specks), sized at half contrast: every equivalent diameter + 2 x ``outline_shift_px``
        (as the profile's median), the area with it."""
        from drgan.metrics.statistics import particles

        found = particles(labels).at_least(min_area_px)
        diameter = self.at_half_contrast(found.diameter)
        return replace(found, diameter=diameter, area=np.pi / 4.0 * diameter**2)

    def at_half_contrast(self, diameter):
        """Equivalent diameters (px) at the segmented outlines moved to half contrast: + 2 x ``outline_shift_px``."""
        return np.maximum(np.asarray(diameter, np.float64) + 2.0 * self.outline_shift_px, 0.0)


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


def _cause(gap: float, classical_px: float, check: Mapping | None, outlines: Mapping | None) -> Verdict | None:
    """Why the two medians disagree, read from the two segmentations of the user's images, and which is trusted (the
    sentence's continuation); None when they agree within ``AGREE`` or the comparison says nothing decisive."""
    if not outlines or not outlines.get("images") or abs(gap) <= AGREE:
        return None
    by_segmenter, by_classical = outlines["merged_by_segmenter"], outlines["merged_by_classical"]
    generated = (check or {}).get("merged")
    n = outlines["images"]
    n_classical, n_segmenter = outlines.get("classical_particles"), outlines.get("segmenter_particles")
    if (
        gap > 0
        and by_segmenter >= by_classical + MERGE_EXCESS
        and by_segmenter >= (generated or 0.0) + MERGE_EXCESS
        and not _outnumbers(n_segmenter, n_classical)
    ):
        unseen = (
            f"; the segmenter merged {_share(generated)} of the generated particles of its check): it merges touching "
            "particles on your images that its check did not see merged"
            if generated is not None
            else "): it merges touching particles that the classical segmentation separates"
        )
        return Verdict(
            f". On your {n} images the segmenter holds {_share(by_segmenter)} of the classical particles in one region "
            f"with a neighbour (the classical segmentation {_share(by_classical)} of the segmenter's{unseen}, so its "
            "particles come out larger and fewer. drgan trusts the classical sizes more; the segmenter's count is low "
            "too. The classical segmentation merges touching particles as well: correct the outlines of one or two "
            'images and fine-tune on them (the pipeline\'s corrected=DIR; docs/pipeline.md, "Correcting outlines": '
            "on TiO2 SEM one corrected image took the median from +24 % to +5 % and the count from -33 % to -1 %), or "
            "score a few annotated images (annotated=), before publishing the count.",
            CLASSICAL,
        )
    if gap < 0 and by_classical >= by_segmenter + MERGE_EXCESS and not _outnumbers(n_classical, n_segmenter):
        return Verdict(
            f". On your {n} images the classical segmentation holds {_share(by_classical)} of the segmenter's particles "
            f"in one region with a neighbour (the segmenter {_share(by_segmenter)} of the classical ones): the "
            "classical sizes are merges. drgan trusts the segmenter's sizes.",
            SEGMENTER,
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
        return Verdict(
            f". The {outlines['matched']} particles both find are {difference:+.1f} px in diameter from the classical "
            f"outlines at half contrast of your images' mean edge{where}. drgan trusts the classical sizes (half "
            "contrast: the boundary of ISO 13322-1 and of drgan's masks).",
            CLASSICAL,
        )
    return None


def _outnumbers(merger: int | None, other: int | None) -> bool:
    """Whether the segmentation that merges the other's particles still finds as many particles or more: then the
    other one misses particles outright, its count is no ceiling and its median is of the particles it found, so the
    merges do not explain the gap (experiments/statistics/trust.md, "Which sizes to trust")."""
    return merger is not None and other is not None and merger >= other


def _merges_outnumbered(gap: float, outlines: Mapping | None) -> str:
    """The sentence for merges that would explain the gap but for the counts (`_outnumbers`); "" where none."""
    if not outlines or not outlines.get("images") or abs(gap) <= AGREE:
        return ""
    counts = {SEGMENTER: outlines.get("segmenter_particles"), CLASSICAL: outlines.get("classical_particles")}
    merger, other = (SEGMENTER, CLASSICAL) if gap > 0 else (CLASSICAL, SEGMENTER)
    share = outlines[f"merged_by_{merger}"]
    if share < MERGE_EXCESS or not _outnumbers(counts[merger], counts[other]):
        return ""
    name = {SEGMENTER: "the segmenter", CLASSICAL: "the classical segmentation"}
    whose = {SEGMENTER: "segmenter's", CLASSICAL: "classical"}
    return (
        f" Merges do not explain the gap: {name[merger]} holds {_share(share)} of the {whose[other]} particles in one "
        f"region with a neighbour, yet finds {counts[merger]} particles to {counts[other]} ({name[other]} misses "
        "particles)."
    )


def _why_biased(check: Mapping) -> str:
    """Where a biased check's error comes from: merged particles or outlines off the true edge."""
    merged, edge = check.get("merged"), check.get("edge_offset_px")
    if merged is not None and merged >= MERGE_EXCESS / 2:
        return f" ({100 * merged:.1f} % of the generated particles merged with a neighbour)"
    if edge is not None and abs(edge) >= 0.5:
        return f" (its outlines {edge:+.2f} px from the true edge)"
    return ""


def _agreement(check: Mapping | None, value: float | None) -> str:
    """The sentence's end where the two medians agree within ``AGREE``."""
    if value is None:
        return f": the two agree within {100 * AGREE:.0f} % (the segmenter has no closed-loop check)."
    if abs(value) <= EXACT:
        return ": the two agree, and the segmenter is exact on generated images. drgan trusts these sizes."
    merged = check.get("merged")
    how = f" ({100 * merged:.1f} % of their particles merged)" if merged is not None else ""
    return (
        f": the two agree within {100 * AGREE:.0f} %, though on generated images the segmenter measures "
        f"{_percent(value)}{how}. Two independent methods agree on your images, so the generated scenes are "
        "harder to measure than yours (their touching particles show no neck the segmenter can cut, e.g. "
        "particles piled over each other) and drgan trusts these sizes; score a few annotated images "
        "(annotated=) to be sure."
    )


def compare_with_classical(
    median_px: float | None, classical_px: float | None, check: Mapping | None, outlines: Mapping | None = None
) -> str:
    """`judge`'s sentence."""
    return judge(median_px, classical_px, check, outlines).sentence


def judge(
    median_px: float | None, classical_px: float | None, check: Mapping | None, outlines: Mapping | None = None
) -> Verdict:
    """The segmenter's median diameter against the profile's classical one (threshold + watershed on the same images,
    no training): whether they agree within the closed-loop interval (widened by ``AGREE``), and where they do not, why
    (``outlines``: `pool`'s comparison of the two segmentations, when measured) and whose sizes drgan trusts."""
    verdict = _judge(median_px, classical_px, check, outlines)
    if median_px and classical_px:
        verdict = replace(
            verdict, sentence=verdict.sentence + _merges_outnumbered(median_px / classical_px - 1, outlines)
        )
    return verdict


def _judge(median_px, classical_px, check, outlines) -> Verdict:
    """`judge` but for the sentence on merges the counts contradict."""
    if not median_px or not classical_px:
        return Verdict("No comparison with the profile's classical sizes (one of the two medians is missing).", None)
    gap = median_px / classical_px - 1.0
    said = (
        f"The segmenter's median diameter ({median_px:.1f} px) is {100 * gap:+.1f} % from the profile's classical one "
        f"({classical_px:.1f} px; threshold + watershed, no training)"
    )
    value = (check or {}).get("median_error", {}).get("value")
    if abs(gap) <= AGREE:  # two independent methods agree on the user's images, whatever the check says
        return Verdict(said + _agreement(check, value), BOTH)
    # what the user's images say (merges either way, outlines off half contrast) comes before the check's interval
    cause = _cause(gap, classical_px, check, outlines)
    if value is not None:
        low, high = _interval(check["median_error"])
        if not low - AGREE <= gap <= high + AGREE:
            said += (
                f", beyond the closed-loop interval [{_percent(low)}, {_percent(high)}] widened by {100 * AGREE:.0f} %"
            )
        elif cause is None and abs(value) <= EXACT:
            return Verdict(
                said + f": within what the closed-loop check allows (the segmenter measures {_percent(value)} "
                f"[{_percent(low)}, {_percent(high)}] on generated images with exact outlines), and your images show "
                "no cause for the gap"
                + ("" if _merges_outnumbered(gap, outlines) else " (no merges either way, outlines at the same edge)")
                + ". drgan trusts the segmenter's sizes.",
                SEGMENTER,
            )
        elif cause is None:
            return Verdict(
                said + f": the gap is what the closed-loop check predicts (the segmenter measures {_percent(value)} on "
                "generated images with exact outlines). drgan trusts the classical sizes more: the segmenter's "
                "sizes carry its own measured error" + _why_biased(check) + ".",
                CLASSICAL,
            )
    if cause:
        return Verdict(said + cause.sentence, cause.trusted)
    if value is None:
        return Verdict(said + "; without a closed-loop check neither can be preferred: look at both overlays.", None)
    if abs(value) <= EXACT:
        return Verdict(
            said + ": the segmenter is exact on generated images, so the gap is either the classical segmentation's "
            "own error (merges, fringes, specks) or a difference between your images and the generated ones at the "
            "particles' edges. drgan trusts the segmenter's sizes (its error is measured, the classical one's is "
            "not); compare the two overlays before publishing.",
            SEGMENTER,
        )
    return Verdict(
        said + f": the segmenter is itself biased ({_percent(value)} on generated images) and disagrees with the "
        "classical sizes by more than that. Neither is trusted: compare the two overlays, or score both on a few "
        "annotated images (annotated=).",
        None,
    )


# the particle table of the sizes analyze reports, by its verdict: (file, diameter column)
TABLES = {CLASSICAL: ("particles_classical.csv", "half_contrast_diameter_px")}
OWN_TABLE = ("particles.csv", "equivalent_diameter_px")


def check_reported(folder) -> Path:
    """``reported=``: an analyze run folder (summary.json, particles.csv), or a ConfigError before any image is read."""
    path = Path(str(folder)).expanduser()
    if not (path / "summary.json").is_file() or not (path / OWN_TABLE[0]).is_file():
        raise ConfigError(f"reported={folder}: expected a drgan.analyze run folder (summary.json, particles.csv in it)")
    return path


def reported_particles(folder: Path, ids: Sequence[str], images_dir: Path) -> Reported | None:
    """The sizes an analyze run reported for the images ``ids`` of ``images_dir``, per image as
    drgan.metrics.statistics.Particles: the table its verdict trusts (``particles_classical.csv``, where it trusted the
    classical sizes; else ``particles.csv``), and which (``classical`` or ``segmenter``). None, logged, when the run
    measured another folder or not every one of ``ids`` (the ids alone could name other images)."""
    from drgan.metrics.statistics import no_particles, read_particle_table

    summary = json.loads((folder / "summary.json").read_text())
    measured_dir = summary.get("images_dir")
    if measured_dir is None or Path(measured_dir).resolve() != Path(images_dir).resolve():
        log.warning(
            "reported=%s measured the images of %s, not the scored %s: its sizes are not scored", folder,
            measured_dir, images_dir,
        )  # fmt: skip
        return None
    if summary.get("exclude_border"):
        log.warning("reported=%s left particles cut by the border out (exclude_border): its count is low", folder)
    trusted = summary.get("trusted")
    which = CLASSICAL if trusted in TABLES and (folder / TABLES[trusted][0]).is_file() else SEGMENTER
    name, column = TABLES.get(which, OWN_TABLE)
    if which == CLASSICAL:
        measured = set((summary.get("classical") or {}).get("segmented") or [])
    else:
        measured = {str(r["image"]) for r in summary.get("per_image") or []}
    missing = [i for i in ids if i not in measured]
    if missing:
        log.warning(
            "reported=%s: its %s sizes do not cover %d of the %d images scored (%s): they are not scored",
            folder, which, len(missing), len(ids), ", ".join(missing[:5]),
        )  # fmt: skip
        return None
    table = read_particle_table(folder / name, column)
    found = [table.get(image_id, no_particles()) for image_id in ids]
    return Reported(which, trusted, found)


@dataclass(frozen=True)
class Reported:
    """`reported_particles`' answer: which table (``classical`` or ``segmenter``), the verdict's ``trusted``, and per
    image the particles (already counted as analyze counts: specks out)."""

    table: str
    trusted: str | None
    particles: list

    def words(self) -> str:
        """What the table is, for statistics.md."""
        if self.table == CLASSICAL:
            return "the profile's classical particles (particles_classical.csv), the sizes it trusted"
        if self.trusted in (SEGMENTER, BOTH):
            return "the segmenter's (particles.csv), the sizes it trusted"
        return "the segmenter's (particles.csv); it trusted neither table over the other"
