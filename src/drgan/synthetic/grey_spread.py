"""Each generated image draws its own grey levels from the real images' spread (`generate grey_spread=true`).

The generator learns one value per scene parameter, so every image of a generated set shows about the same
background grey and particle contrast, while real micrographs vary from image to image (illumination, detector
settings, film thickness), so the generated set's background grey spans a narrower range than the real windows'
(experiments/realism/README.md). A segmenter trained on the narrow set calls the darkest real images all particle and
the brightest all background.

With grey_spread, image i takes the (background, particle) grey of one real *train* patch, drawn with the
image's own seed, and its grey levels are mapped by the affine function that sends its own background and
particle grey (from its labels) there: x -> b' + (x - b) (p' - b') / (p - b), clipped to [0, 1].
Both sides measure alike (`grey_levels`): medians of the background beyond EDGE_MARGIN px from any particle and of
the particles' cores (EDGE_MARGIN px in). Means over the whole classes were biased on the real side, whose classical
foreground is not the true outline: it leaves the particles' bright edges and dim parts to the background, whose
mean then comes out too bright for the darkest windows.
Labels do not change; noise and texture scale with the contrast, as they do in a real image. The real patches'
levels come from drgan's classical segmentation with the patch set's own settings (no annotation is read), with the
threshold's own outlines (not grown to the edges: a core's median, the dim edge left out); and the generated image's
own levels are measured by that same segmentation
(`GreySpread`), not by its exact labels: the classical outline is an Otsu threshold, tighter than a particle's true
outline where its edge is dim, so its core median is brighter. Measured by labels on one side and the classical
outline on the other, that bias becomes too much contrast in every generated image; measured alike on both sides, it
cancels (experiments/realism/README.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from drgan.core.errors import DataError

if TYPE_CHECKING:
    from drgan.data.classical import SegmentParams

MIN_SHARE = 0.02  # a patch counts only when particles and background each cover at least this share of it
EDGE_MARGIN = 2  # px: edges (blur, SEM edge brightening, a classical outline's offset) are left out of both levels


def away_from_edges(particle: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """(background, core): the pixels farther than ``margin`` px from any ``particle`` pixel, and the particle pixels
    ``margin`` px inside their outline (``margin`` 0: the two classes themselves)."""
    from scipy import ndimage as ndi

    particle = np.asarray(particle, bool)
    if margin <= 0:  # (iterations=0 would mean "until nothing changes")
        return ~particle, particle
    return ~ndi.binary_dilation(particle, iterations=margin), ndi.binary_erosion(
        particle, iterations=margin, border_value=1
    )


def grey_levels(image: np.ndarray, particle: np.ndarray, margin: int = EDGE_MARGIN) -> tuple[float, float]:
    """(background, particle) grey of ``image``: the median of the pixels farther than ``margin`` px from any
    ``particle`` pixel, and the median of the particle pixels ``margin`` px inside their outline (all of either
    class where nothing is left of it: `away_from_edges`)."""
    particle = np.asarray(particle, bool)
    far, inner = away_from_edges(particle, margin)
    background = far if far.any() else ~particle
    core = inner if inner.any() else particle
    return float(np.median(image[background])), float(np.median(image[core]))


def classical_particles(image: np.ndarray, segment, polarity: str) -> np.ndarray | None:
    """bool: the particles drgan's classical segmentation (``segment``: SegmentParams or a data.segment mapping)
    finds in ``image``, or None unless particles and background each cover at least MIN_SHARE of it."""
    from drgan.data.classical import particle_foreground

    particle = particle_foreground(image, segment, polarity)
    return particle if MIN_SHARE <= particle.mean() <= 1 - MIN_SHARE else None


def patch_grey_levels(patches: np.ndarray, segment, polarity: str) -> np.ndarray:
    """(N, 2) (background, particle) grey (`grey_levels`) of each patch in which both are shown (others left out)."""
    from drgan.data.classical import SegmentParams

    params = SegmentParams.from_config(segment)
    levels = []
    for patch in np.asarray(patches, dtype=np.float32):
        particle = classical_particles(patch, params, polarity)
        if particle is not None:
            levels.append(grey_levels(patch, particle))
    if not levels:
        raise DataError(
            f"grey_spread: none of the {len(patches)} real patches shows both particles and background (classical "
            "segmentation with the patch set's settings); set grey_spread=false"
        )
    return np.asarray(levels, dtype=np.float64)


def match_grey(
    image: np.ndarray, labels: np.ndarray, target: tuple[float, float], margin: int = EDGE_MARGIN
) -> np.ndarray:
    """``image`` with its background and particle grey (`grey_levels` of ``labels`` > 0) moved to ``target``
    (background, particle) by one affine grey map, clipped to [0, 1]. Unchanged when either is missing or they are
    equal."""
    image = np.asarray(image, dtype=np.float32)
    particle = np.asarray(labels) > 0
    if not particle.any() or particle.all():
        return image
    background_grey, particle_grey = grey_levels(image, particle, margin)
    if abs(particle_grey - background_grey) < 1e-6:
        return image
    new_background, new_particle = target
    gain = (new_particle - new_background) / (particle_grey - background_grey)
    return np.clip(new_background + (image - background_grey) * gain, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class GreySpread:
    """The real train patches' grey levels and the segmentation that measured them, ready to move a generated
    image's levels onto one drawn patch's (`apply`)."""

    levels: np.ndarray  # (N, 2) (background, particle) grey of the real patches that show both
    segment: SegmentParams  # the patch set's settings, at the generated images' px
    polarity: str  # the particles' side of the grey scale: "bright" or "dark"

    @classmethod
    def from_patches(cls, patches: np.ndarray, segment: dict, polarity: str, resolution: int) -> GreySpread:
        """From (N, S, S) real patches segmented with ``segment`` (the patch set's settings, at S px; the outlines
        not grown): the settings scaled to generated images of ``resolution`` px. Settings not resolved (a patch set
        older than a key, or made by hand) are resolved once on the patches, so that every patch and every generated
        image is segmented alike (not each at a scale of its own)."""
        from drgan.data.classical import resolve_params

        params, _ = resolve_params(list(np.asarray(patches, dtype=np.float32)), segment, polarity)
        # The threshold's own outline, not grown to the edges (`grow_to_edges`): a level is a core's median, and the
        # grown outline takes in the dim edge, which a render and a micrograph fade through unlike each other (grown on
        # both sides, the generated contrast's low end comes out too high; experiments/realism/README.md).
        params = replace(params, grow_outlines=False)
        levels = patch_grey_levels(patches, params, polarity)
        return cls(levels, params.scaled(resolution / np.shape(patches)[-1]), polarity)

    def particles(self, image: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, str]:
        """(particle pixels, "classical" or "labels"): where the real patches' segmentation finds particles and
        background in ``image`` (each at least MIN_SHARE), its foreground, measured as the real levels were;
        otherwise the exact labels."""
        foreground = classical_particles(image, self.segment, self.polarity)
        if foreground is not None:
            return foreground, "classical"
        return np.asarray(labels) > 0, "labels"

    def apply(self, image: np.ndarray, labels: np.ndarray, seed: int) -> tuple[np.ndarray, dict]:
        """(``image`` with its levels moved to those of the real patch drawn with ``seed``, what was done: the
        target levels and which pixels measured the image's own)."""
        target = draw(self.levels, seed)
        particle, measured_by = self.particles(image, labels)
        info = {"target": [round(float(v), 4) for v in target], "measured_by": measured_by}
        return match_grey(image, particle, target), info


def draw(levels: np.ndarray, seed: int) -> tuple[float, float]:
    """One real patch's (background, particle) grey, drawn with ``seed`` (the image's own)."""
    return tuple(levels[np.random.default_rng(seed).integers(len(levels))])
