"""What `python -m drgan.profile` measured on a folder of real images: `ProfileResult`, typed by section.

profile.json is `ProfileResult.as_dict` (each section's keys in its fields' order); report.md and the material
proposal (drgan.profiling.proposal) read the typed sections; `ProfileResult.from_dict` reads a profile.json back.
Values are as profile.json records them (rounded where it rounds them), so that what the report and the material
config say is what profile.json holds. The records of objects typed elsewhere stay the dicts they write: the scale
search (`drgan.data.classical`), the segmentation parameters, the size fits (`drgan.data.measurements.SizeFit`),
the polarity estimate and the edge profile (`drgan.data.particle_edge`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass

from drgan.data.measurements import NoiseEstimate


@dataclass(frozen=True)
class ImagesRead:
    """``data``: the images profiled."""

    dir: str  # the folder, resolved
    crop_rows: list[int] | str | None  # [start, stop), "auto" (each image's info bar) or None
    split: str | None  # the split file whose train ids were read, resolved
    images: int
    ids: list[str]  # file stems, in the order read
    shape: list[int]  # (rows, columns) of the first image, cropped


@dataclass(frozen=True)
class PolarityFound:
    """``polarity``: the particles' polarity, and how it was found."""

    value: str  # bright | dark
    setting: str  # data.polarity: auto (detected) | bright | dark
    estimate: dict = field(default_factory=dict)  # drgan.data.polarity's estimate record (empty when set)

    @property
    def confidence(self):
        """The detection's confidence ("-" when the polarity was set)."""
        return self.estimate.get("confidence", "-")

    def as_dict(self) -> dict:
        return {"value": self.value, "setting": self.setting, **self.estimate}

    @classmethod
    def from_dict(cls, record: dict) -> PolarityFound:
        rest = dict(record)
        return cls(rest.pop("value"), rest.pop("setting"), rest)


@dataclass(frozen=True)
class SegmentationFound:
    """``segmentation``: the particle scale and the classical segmentation that ran with it."""

    scale_px: float
    scale_estimate: dict | None  # the scale search's record (None when data.segment.scale was given)
    setting: dict  # the data.segment keys given by hand (those not at SegmentParams' defaults)
    separability_median: float  # Otsu separability, median over the images
    outlines_grown: dict  # images whose outlines grew to the particles' edges, foreground_added_median
    params: dict  # the SegmentParams used
    particles: int  # segments, all images
    particles_not_touching_border: int


@dataclass(frozen=True)
class SizesFound:
    """``sizes``: equivalent diameters of the particles not touching the border, at half contrast (the segmented
    outlines moved by ``outline_shift_px``), and the fits."""

    median_diameter_px: float
    mean_diameter_px: float
    quantiles_px: dict  # "0.1", "0.25", "0.75", "0.9" -> px
    fits: list[dict]  # SizeFit records: kind, params, log_likelihood, bic, ...
    chosen: str  # the kind of the fit chosen
    criterion: str
    # px from the segmented outline to half contrast (> 0 outwards): every diameter above is the segmented one + 2 x
    # this. Profiles written before it measured at the segmented outline: 0.
    outline_shift_px: float = 0.0
    segmented_median_diameter_px: float | None = None  # the median at the segmented outline


@dataclass(frozen=True)
class PatchCounts:
    """``particles_per_patch``: segments per training-sized window."""

    definition: str
    patch_size: int
    windows: int
    mean: float
    median: float
    p10: float
    p90: float
    with_3_or_more: dict  # windows, p10, p90 of the windows training keeps (data.min_particles: 3)
    render_px: int | None = None  # the render size when the window is wider (large particles; None: the same)
    # windows of the training grid (stride, windows) and how many show >= 1, 2, 3 whole particles (as mining counts)
    whole: dict | None = None
    # windows, p10, p90 of the windows with >= k particles, k = "1", "2", "3": the range of the windows training keeps
    # when the profile lowers data.min_particles to k (None: profiles from before; with_3_or_more holds k = 3)
    kept_counts: dict | None = None


@dataclass(frozen=True)
class Agglomeration:
    """``agglomeration``: how the particles lie."""

    touching_fraction: float
    clark_evans_median: float | None
    placement: str  # the placement group proposed


@dataclass(frozen=True)
class ShapeFound:
    """``shape``: how elongated the particles are."""

    axis_ratio_median: float
    mesh_kind: str  # the mesh kind proposed


@dataclass(frozen=True)
class PixelSize:
    """``pixel_size``: nm per px where the images say it."""

    nm_per_px: float | None
    source: str
    images_with_size: int


@dataclass(frozen=True)
class MaterialProposed:
    """``material``: the config written (drgan.profiling.proposal)."""

    parent: str  # the paper material it inherits
    config: str  # the file written, resolved
    data: dict  # its data keys (segmentation, mining)
    fringe: dict | None  # material.imaging.fringe as written (None: the material renders no fringe)


@dataclass(frozen=True)
class ProfileResult:
    """Everything one profile measured; the fields in profile.json's order."""

    name: str
    data: ImagesRead
    polarity: PolarityFound
    segmentation: SegmentationFound
    background: NoiseEstimate  # as recorded (rounded to 6 decimals)
    sizes: SizesFound
    particles_per_patch: PatchCounts
    agglomeration: Agglomeration
    shape: ShapeFound
    edge: dict | None  # the mean edge profile's record (None: too few isolated particles)
    pixel_size: PixelSize
    out: str  # the profile's folder, resolved
    material: MaterialProposed | None = None  # None until the material config is written
    edge_blur_px: float | None = None  # outlines' blur, px of the images (measurements.edge_blur; median of images)

    def as_dict(self) -> dict:
        """profile.json."""
        return {f.name: _record(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_dict(cls, record: dict) -> ProfileResult:
        """From a profile.json (`as_dict`)."""
        material = record.get("material")
        return cls(
            name=record["name"],
            data=ImagesRead(**record["data"]),
            polarity=PolarityFound.from_dict(record["polarity"]),
            segmentation=SegmentationFound(**record["segmentation"]),
            background=NoiseEstimate(**record["background"]),
            sizes=SizesFound(**record["sizes"]),
            particles_per_patch=PatchCounts(**record["particles_per_patch"]),
            agglomeration=Agglomeration(**record["agglomeration"]),
            shape=ShapeFound(**record["shape"]),
            edge=record.get("edge"),
            pixel_size=PixelSize(**record["pixel_size"]),
            out=record["out"],
            material=MaterialProposed(**material) if material is not None else None,
            edge_blur_px=record.get("edge_blur_px"),
        )


def _record(value):
    """A section as profile.json holds it: its own ``as_dict`` where it has one, else its fields in order."""
    if hasattr(value, "as_dict"):
        return value.as_dict()
    if is_dataclass(value):
        return {f.name: getattr(value, f.name) for f in fields(value)}
    return value
