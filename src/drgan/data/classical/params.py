"""The classical segmentation's settings (`SegmentParams`: a material's ``data.segment``), and its one error."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING

from drgan.core.errors import ConfigError, DataError
from drgan.data.classical.calibration import CALIBRATION as CAL

if TYPE_CHECKING:
    from drgan.data.classical.scale import ScaleEstimate


@dataclass(frozen=True)
class SegmentParams:
    """Classical particle segmentation; lengths in pixels, areas in square pixels.

    Every length left None follows from the particle diameter ``scale`` (itself estimated from the image when
    None): see `resolved`. A value given is used exactly as given.
    """

    scale: float | None = None  # particle diameter, px; None: estimated (`estimate_scale`)
    # None below: from the scale, by the fractions of Calibration (sigma_per_diameter, ...)
    sigma: float | None = None  # Gaussian smoothing before thresholding, px
    min_distance: int | None = None  # least distance between watershed seeds, px
    min_area: int | None = None  # smaller segments are noise, specks or slivers, px^2 (a disc's area)
    max_area: int | None = None  # larger segments are unsplit agglomerates, px^2 (a disc's area)
    background: float | None = None  # illumination flattened at this size, px (0: not)
    annotations: bool = True  # find scale bars, text and panel letters, and leave them out
    # A watershed seed must stand this many px above the saddle to its neighbour in the foreground's distance
    # transform (h-maxima). Thin foreground (film wrinkles and lines, grain strands, rims) has a maximum every
    # min_distance along its length, each < 1 px deep, and breaks into particle-sized "segments" that pull the
    # measured scale down; 1 px keeps them whole but also merges touching particles whose necks are as shallow
    # (TiO2's), so it is off by default: a key to set for images with strands. 0: every maximum seeds.
    seed_depth: float = 0.0
    # A watershed seed must stand this share of its own height above the saddle to a higher peak of the distance
    # transform (its neck; `_neck_caps`): touching particles mostly meet at deep necks, while a rod's ridge and an
    # irregular particle's bumps rise a few % above theirs, so Calibration.neck_depth keeps rods and irregular
    # particles whole; but annotators split agglomerated particles at necks as shallow, which it merges. 0: every
    # maximum min_distance apart seeds. None (the default): 0 or Calibration.neck_depth, searched with the scale:
    # the one whose segments persist over more scales and are more alike in size (`search_scale`).
    neck_depth: float | None = None
    # Segments grow out to the particles' strongest edges where those lie below Otsu's threshold (`grow_to_edges`);
    # False: Otsu's outlines.
    grow_outlines: bool = True
    # Otsu's between-class / total variance around the blobs of the particles' size: smoothed noise scores 2/pi at
    # any scale, particles at their own scale more. Left at the default, the scale search may lower it for a dense
    # packing of alike particles (`search_scale`).
    min_separability: float = CAL.min_separability

    def __post_init__(self) -> None:
        for key in ("scale", "sigma", "background"):
            value = getattr(self, key)
            if value is not None and not (isinstance(value, (int, float)) and value >= 0 and math.isfinite(value)):
                raise ConfigError(f"data.segment.{key}={value!r}: expected a number >= 0 (px) or null (from the scale)")
        if self.scale is not None and self.scale <= 0:
            raise ConfigError(f"data.segment.scale={self.scale}: expected a particle diameter > 0 px or null")
        if self.min_distance is not None and self.min_distance < 1:
            raise ConfigError(f"data.segment.min_distance={self.min_distance}: expected >= 1 px or null")
        low, high = self.min_area, self.max_area
        if (low is not None and low <= 0) or (low is not None and high is not None and low > high):
            raise ConfigError(
                f"data.segment min_area={low}, max_area={high}: expected 0 < min_area <= max_area (px^2) or null"
            )
        if self.neck_depth is not None and not (isinstance(self.neck_depth, (int, float)) and 0 <= self.neck_depth < 1):
            raise ConfigError(
                f"data.segment.neck_depth={self.neck_depth!r}: expected a share of a seed's height in [0, 1), or null"
                " (chosen from the images)"
            )
        if not (isinstance(self.seed_depth, (int, float)) and 0 <= self.seed_depth < math.inf):
            raise ConfigError(f"data.segment.seed_depth={self.seed_depth!r}: expected a depth >= 0 px")
        if not isinstance(self.grow_outlines, bool):
            raise ConfigError(f"data.segment.grow_outlines={self.grow_outlines!r}: expected true or false")
        if not 0 <= self.min_separability < 1:
            raise ConfigError(f"data.segment.min_separability={self.min_separability}: expected in [0, 1)")

    @classmethod
    def from_config(cls, segment) -> SegmentParams:
        """From a ``data.segment`` mapping (None or {} = everything from the image); unknown keys are named."""
        if isinstance(segment, SegmentParams):
            return segment
        values = dict(segment or {})
        unknown = sorted(set(values) - set(cls.__dataclass_fields__))
        if unknown:
            raise ConfigError(
                f"data.segment: unknown key(s) {unknown}; expected some of {', '.join(cls.__dataclass_fields__)}"
            )
        return cls(**values)

    @property
    def is_resolved(self) -> bool:
        lengths = (self.scale, self.sigma, self.min_distance, self.min_area, self.max_area, self.background)
        return None not in (*lengths, self.neck_depth)

    def resolved(self, scale: float | None = None) -> SegmentParams:
        """Every length set: those given kept, the others from ``scale`` (or self.scale), the particle diameter. A
        neck depth left None becomes 0 here (every maximum seeds): `resolve_params` chooses it from images."""
        d = float(self.scale if self.scale is not None else scale) if (self.scale or scale) else None
        if d is None:
            raise ConfigError("SegmentParams.resolved: no particle scale (give data.segment.scale or an image)")
        d = round(d, 2)  # the lengths follow from the scale as recorded: set by hand, it resolves to the same
        min_area = self.min_area or max(4, int(round(math.pi / 4 * (CAL.min_area_diameter * d) ** 2)))
        max_area = self.max_area or max(min_area, int(round(math.pi / 4 * (CAL.max_area_diameter * d) ** 2)))
        return replace(
            self,
            scale=d,
            sigma=self.sigma if self.sigma is not None else round(CAL.sigma_per_diameter * d, 2),
            min_distance=self.min_distance or max(1, int(round(CAL.min_distance_per_diameter * d))),
            min_area=min_area,
            max_area=max_area,
            background=self.background if self.background is not None else round(CAL.background_per_diameter * d, 1),
            neck_depth=self.neck_depth or 0.0,
        )

    def scaled(self, factor: float) -> SegmentParams:
        """The same settings for the image resized by ``factor`` (e.g. patches area-averaged from a window of W px
        to S px: factor S / W): lengths times factor, areas times factor squared; None stays None."""
        if not (factor > 0 and math.isfinite(factor)):
            raise ConfigError(f"SegmentParams.scaled: factor={factor!r}, expected a number > 0")
        if factor == 1:
            return self

        def length(value):
            return None if value is None else round(float(value) * factor, 2)

        def area(value):
            return None if value is None else max(1, int(round(value * factor * factor)))

        return replace(
            self,
            scale=length(self.scale),
            sigma=length(self.sigma),
            min_distance=None if self.min_distance is None else max(1, int(round(self.min_distance * factor))),
            min_area=area(self.min_area),
            max_area=area(self.max_area),
            background=length(self.background),
        )

    def as_dict(self) -> dict:
        return asdict(self)


class NoParticles(DataError):
    """No particle found; the message says what was tried and which keys to set. ``search``: the scale search's
    `ScaleEstimate` (its grid and fixed points) where one ran."""

    def __init__(self, what: str, params: SegmentParams, search: ScaleEstimate | None = None):
        self.what, self.params, self.search = what, params, search
        super().__init__(
            f"no particles found: {what}. Set the particle size by hand with data.segment.scale=DIAMETER_PX (and, "
            "if needed, data.segment.sigma, min_distance, min_area, max_area, min_separability), or data.polarity="
            "bright|dark when the particles' side of the grey scale was misread"
        )
