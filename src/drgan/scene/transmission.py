"""Transmission contrast (TEM, STEM bright field, transmission SEM): dark particles on a bright film.

The beam crosses the sample; a pixel darkens with the material its electrons cross, whatever the surface
does. So the scene needs no lights, BSDFs or integrator: per pixel, ``spp`` stratified camera rays (the
camera of `ParticleScene`), and for each ray the total path length t inside the particle meshes, summed
over every entry/exit pair along it (overlapping particles add). The image is

    floor + (background - floor) * mean over the pixel's rays of exp(-absorption * t)

then the Gaussian reconstruction blur of the SEM scene (`reconstruction_blur`). ``background`` is the grey
of the bare film, ``absorption`` the attenuation per px of path length, ``floor`` the grey behind an opaque
particle (detector offset). A material with a ``fringe`` (measured by `drgan.profile`) adds, before the blur,
the defocus fringe at the particles' edges: ``fringe_amplitude`` x `edge_fringe` of the darkening (background
minus grey), a Laplacian-of-Gaussian ring; without one nothing is added and no parameter exists. t depends on
the layout alone, so it is traced once per layout (Dr.Jit, all rays at once) and cached; the image is then a
plain torch function of the three (four) values, and autograd gives its exact gradient (no adjoint pass, no
Monte Carlo noise: ``spp`` only antialiases the edges).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh

from drgan.core.errors import ConfigError, MeshError, check_spp
from drgan.scene.config import Material, TransmissionImaging, register_scene
from drgan.scene.parameters import MaterialParameters, Parameter
from drgan.scene.scene import MeshParticles, RenderSettings, dr, gaussian_kernel, mi, reconstruction_blur

PARAMETERS = ("background", "absorption", "floor")  # the scene's values, in the FCN's output order
FRINGE_PARAMETER = "fringe_amplitude"  # after them, only in a material with a fringe
PHI_1 = math.exp(-0.5) / math.sqrt(2.0 * math.pi)  # the standard normal density at 1: a ring's peak scale


@dataclass(frozen=True)
class TransmissionSpec:
    """What a transmission scene needs: its parameters, the render settings (resolution, spp,
    filter_stddev and camera_distance are used), the width of the view in px of the real image, and the edge
    fringe's width (px of the real image; None: no fringe, and no fringe amplitude among the parameters)."""

    parameters: MaterialParameters
    render: RenderSettings = field(default_factory=RenderSettings)
    view_width: float = 256.0
    fringe_width_px: float | None = None

    def __post_init__(self):
        if not self.view_width > 0:
            raise ConfigError(f"view_width={self.view_width}: expected > 0 (pixels of the real image)")
        expected = PARAMETERS + ((FRINGE_PARAMETER,) if self.fringe_width_px is not None else ())
        names = tuple(p.name for p in self.parameters.bsdf)
        others = sorted(p.key for p in self.parameters.bsdf if p.surface != "transmission")
        if others or names != expected:
            raise ConfigError(
                f"transmission scene: expected the parameters {', '.join(expected)} "
                f"(material.imaging), got {', '.join(p.key for p in self.parameters.bsdf) or 'none'}"
            )
        if self.fringe_width_px is not None and not (math.isfinite(self.fringe_width_px) and self.fringe_width_px > 0):
            raise ConfigError(f"material.imaging.fringe.width_px={self.fringe_width_px}: expected a finite number > 0")

    @property
    def fringe_width_render_px(self) -> float | None:
        """The fringe's width in render px (the material gives it in px of the real image)."""
        if self.fringe_width_px is None:
            return None
        return self.fringe_width_px * self.render.resolution / self.view_width


def log_kernels(width: float, dtype=torch.float32, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(g, g2): the sampled 1-D Gaussian of stddev ``width`` px and its second derivative, g2 corrected to sum 0
    (a constant map gets no fringe) and to second moment sum x^2 g2 = 2 (the continuous one's: a quadratic map
    gets its exact second derivative), so that g2 (x) g + g (x) g2 is the Laplacian of the Gaussian blur also when
    ``width`` is near a pixel."""
    g = gaussian_kernel(width, dtype, device)
    radius = (len(g) - 1) // 2
    x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    g2 = g * (x * x - width * width) / width**4
    g2 = g2 - g * g2.sum()
    return g, g2 * (2.0 / (x * x * g2).sum())


def edge_fringe(contrast: torch.Tensor, width: float) -> torch.Tensor:
    """w^2 / phi(1) x Laplacian(G_w * contrast) of an (H, W) map, ``width`` = w in its px: the defocus term of the
    weak-phase picture (proportional to the Laplacian of the projected sample), seen through a Gaussian of
    stddev w. Outside a straight step of height 1 (contrast 1 inside, 0 outside) it is s phi(s / w) / (w phi(1))
    at distance s: a ring of peak +1 at s = w, with a ring of -1 at w inside; it sums to 0 over any constant
    region. Borders replicate the edge pixels. Linear in ``contrast`` and differentiable."""
    g, g2 = log_kernels(width, contrast.dtype, contrast.device)
    radius = (len(g) - 1) // 2
    padded = torch.nn.functional.pad(contrast[None, None], (radius,) * 4, mode="replicate")
    # Two separable passes: d2/dx2 of the y-blurred map, plus d2/dy2 of the x-blurred map.
    blur_y = torch.nn.functional.conv2d(padded, g.view(1, 1, -1, 1))
    blur_x = torch.nn.functional.conv2d(padded, g.view(1, 1, 1, -1))
    laplacian = torch.nn.functional.conv2d(blur_y, g2.view(1, 1, 1, -1)) + torch.nn.functional.conv2d(
        blur_x, g2.view(1, 1, -1, 1)
    )
    return laplacian[0, 0] * (width * width / PHI_1)


def stratified_offsets(spp: int) -> np.ndarray:
    """(spp, 2) sub-pixel positions: the centres of a sqrt(spp) x sqrt(spp) grid of strata over the pixel."""
    k = math.isqrt(check_spp(spp, "spp"))
    centres = (np.arange(k) + 0.5) / k
    x, y = np.meshgrid(centres, centres, indexing="xy")
    return np.stack([x.ravel(), y.ravel()], axis=1).astype(np.float32)


def outward(mesh: trimesh.Trimesh, index: int) -> trimesh.Trimesh:
    """The mesh with its faces wound outwards (entry and exit are told by the face normal); closed meshes only."""
    if not mesh.is_watertight:
        raise MeshError(
            f"particle mesh {index}: not closed (watertight); a transmission scene measures path lengths inside "
            "particles, which needs closed meshes"
        )
    if mesh.volume < 0:
        mesh = mesh.copy()
        mesh.invert()
    return mesh


def farthest_outline_labels(silhouettes: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """(H, W, n) bool silhouettes (particle k covers the pixel) -> (H, W) int32 labels 1..n, 0 off every silhouette:
    each covered pixel to the particle whose own outline is farthest from it (Euclidean distance transform of its
    silhouette; ties to the lower id), ``fallback``'s label where no silhouette covers a pixel it labels. The image
    border is no outline: a silhouette cut by it is continued (edge padding)."""
    from scipy import ndimage

    height, width, n = silhouettes.shape
    best = np.zeros((height, width), np.float32)
    labels = np.zeros((height, width), np.int32)
    for k in range(n):
        rows, cols = np.nonzero(silhouettes[:, :, k].any(axis=1))[0], np.nonzero(silhouettes[:, :, k].any(axis=0))[0]
        if len(rows) == 0:
            continue
        # its box and one pixel more (outside it: not the particle), padded by repetition at the image border
        y0, y1 = max(rows[0] - 1, 0), min(rows[-1] + 2, height)
        x0, x1 = max(cols[0] - 1, 0), min(cols[-1] + 2, width)
        box = np.pad(silhouettes[y0:y1, x0:x1, k], 1, mode="edge")
        inner = ndimage.distance_transform_edt(box)[1:-1, 1:-1]
        region_best, region_labels = best[y0:y1, x0:x1], labels[y0:y1, x0:x1]
        wins = inner > region_best
        region_best[wins], region_labels[wins] = inner[wins], k + 1
    return np.where(labels > 0, labels, fallback).astype(np.int32)


@register_scene
class TransmissionScene(MeshParticles):
    """n particle meshes seen in transmission (`drgan.scene.protocol.Scene`; ``learned``: the learned ones of
    background, absorption, floor and, with a fringe, its amplitude, in that order)."""

    Config = TransmissionImaging

    @classmethod
    def spec_from_config(cls, material: Material, render: RenderSettings) -> TransmissionSpec:
        imaging: TransmissionImaging = material.imaging
        parameters = imaging.material_parameters(material.noise_sigma)
        return TransmissionSpec(
            parameters=parameters,
            render=render,
            view_width=float(material.view_width),
            fringe_width_px=float(imaging.fringe.width_px) if imaging.fringe is not None else None,
        )

    def __init__(
        self, meshes: Sequence[trimesh.Trimesh], n_particles: int, spec: TransmissionSpec, variant: str = "auto"
    ):
        if not isinstance(spec, TransmissionSpec):
            raise ConfigError(f"TransmissionScene: expected a TransmissionSpec, got {type(spec).__name__}")
        self._learned = spec.parameters.learned_bsdf
        self._thickness: dict[int, torch.Tensor] = {}  # spp -> (H * W, spp) path lengths of the current layout
        # spp -> (pixels some ray of which crosses a particle, their path lengths)
        self._covered: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        super().__init__([outward(m, i) for i, m in enumerate(meshes)], n_particles, spec, variant)

    def _scene_dict(self) -> dict:
        return {"type": "scene", "sensor": self._sensor_dict(), "particles": self.particles}

    def _layout_changed(self) -> None:
        self._thickness, self._covered = {}, {}

    @property
    def learned(self) -> tuple[Parameter, ...]:
        return self._learned

    # -- path lengths ---------------------------------------------------------------------------
    def thickness(self, spp: int | None = None) -> torch.Tensor:
        """(H * W, spp) float32: path length (px) inside particles of each camera ray, rows = pixels row-major.

        Traced on the first call per layout and spp, then cached (a copy is not made: do not modify it).
        """
        if self._layout is None:
            raise RuntimeError("set_layout(phi_i) before thickness() or render()")
        spp = self.spec.render.spp if spp is None else check_spp(spp, "spp")
        if spp not in self._thickness:
            self._thickness[spp] = self._trace_thickness(spp)
        return self._thickness[spp]

    def _trace_thickness(self, spp: int) -> torch.Tensor:
        """Walk every ray through all surfaces it crosses, all rays at once.

        Along a ray, each hit either enters a particle (geometric normal against the ray) or leaves one;
        ``depth`` counts how many particles the ray is inside, and each segment between two hits adds its
        length x depth (two overlapping particles count twice). Depth never drops below 0, and a segment
        after the last hit adds nothing, so a hit lost at a grazing edge costs at most that one segment instead
        of a path length of the camera distance. Rays that hit nothing more are dropped (``dr.compress``), so
        each pass traces only the rays still inside the cluster. At most 2 x n_particles + 2 passes: a ray
        crosses each closed particle surface an even number of times, twice for convex ones.
        """
        with dr.suspend_grad():
            ray, _ = self.camera_rays(stratified_offsets(spp))
            n_rays = dr.width(ray.o)
            total = dr.zeros(mi.Float, n_rays)
            index = dr.arange(mi.UInt32, n_rays)
            origin, direction = mi.Point3f(ray.o), dr.normalize(mi.Vector3f(ray.d))
            ray = mi.Ray3f(origin, direction)
            length, depth, last = (dr.zeros(mi.Float, n_rays) for _ in range(3))
            for _ in range(2 * self.n_particles + 2):
                si = self.scene.ray_intersect(ray, mi.RayFlags.Minimal, False)
                hit = si.is_valid()
                t = dr.dot(si.p - origin, direction)  # from the camera ray's own origin: no drift across spawns
                length = length + dr.select(hit, (t - last) * depth, 0.0)
                depth = dr.select(dr.dot(si.n, direction) < 0, depth + 1.0, dr.maximum(depth - 1.0, 0.0))
                start = si.spawn_ray(direction).o
                # One kernel per pass: the intersection is traced once, not once per array read below.
                dr.eval(hit, t, length, depth, start)
                dr.scatter(total, length, index)  # each ray owns one slot: a plain write, no atomics
                keep = dr.compress(hit)
                if dr.width(keep) == 0:
                    break
                index, origin, direction, start = (
                    dr.gather(type(v), v, keep) for v in (index, origin, direction, start)
                )
                length, depth, last = (dr.gather(mi.Float, v, keep) for v in (length, depth, t))
                ray = mi.Ray3f(start, direction)
            size = self.spec.render.resolution
            return torch.from_numpy(np.array(total, dtype=np.float32).reshape(size * size, spp))

    def _trace_labels(self) -> np.ndarray:
        """Instance labels in transmission: a pixel inside several particles' silhouettes belongs to the one whose own
        outline lies farthest from it (the first hit where no silhouette can be told).

        A transmission image is the same whichever of two overlapping particles lies in front (path lengths add; a
        thick particle is black either way), so the first-hit labels of an opaque scene would draw the overlap's
        outline along the front particle's arc: a line the image does not show, which no segmenter can learn (on
        generated TSEM pairs the networks merged overlapping particles instead). What the image shows is the union of
        the silhouettes and its necks; the farthest-outline rule cuts an overlap along the curve where the two
        silhouettes' inner distances are equal, which runs from one crossing of the outlines to the other (for two
        discs of radii r1, r2 at distances d1, d2: r1 - d1 = r2 - d2), as annotators cut touching particles at the
        neck. Pixels of one particle keep their label.

        Silhouettes: per camera ray (one through each pixel centre) every surface crossing adds +1 (entry) or -1
        (exit) to its particle's count and -t or +t to its path; the ray crossed particle k when its entries and exits
        pair up and its path is positive (a hit lost at a grazing edge leaves the ray its first hit's label). The image
        border is no outline (a particle cut by it continues beyond)."""
        size, n = self.spec.render.resolution, self.n_particles
        with dr.suspend_grad():
            ray, _ = self.camera_rays([(0.5, 0.5)])
            n_rays = dr.width(ray.o)
            path = dr.zeros(mi.Float, n_rays * n)  # per (ray, particle): sum of exit t - entry t
            balance = dr.zeros(mi.Int32, n_rays * n)  # entries minus exits: 0 when every entry found its exit
            first = dr.zeros(mi.UInt32, n_rays)
            index = dr.arange(mi.UInt32, n_rays)
            origin, direction = mi.Point3f(ray.o), dr.normalize(mi.Vector3f(ray.d))
            ray = mi.Ray3f(origin, direction)
            for crossing in range(2 * n + 2):
                si = self.scene.ray_intersect(ray, mi.RayFlags.Minimal, False)
                hit = si.is_valid()
                label = dr.gather(mi.UInt32, self._face_label, si.prim_index, hit)
                t = dr.dot(si.p - origin, direction)
                entering = dr.dot(si.n, direction) < 0
                slot = index * n + (label - 1)
                dr.scatter_add(path, dr.select(entering, -t, t), slot, hit)
                dr.scatter_add(balance, dr.select(entering, mi.Int32(1), mi.Int32(-1)), slot, hit)
                if crossing == 0:
                    first = dr.select(hit, label, 0)
                start = si.spawn_ray(direction).o
                dr.eval(hit, start, path, balance, first)
                keep = dr.compress(hit)
                if dr.width(keep) == 0:
                    break
                index, origin, direction, start = (
                    dr.gather(type(v), v, keep) for v in (index, origin, direction, start)
                )
                ray = mi.Ray3f(start, direction)
            lengths = np.array(path, dtype=np.float32).reshape(size, size, n)
            paired = np.array(balance, dtype=np.int32).reshape(size, size, n) == 0
            labels = np.array(first, dtype=np.int32).reshape(size, size)
        return farthest_outline_labels(paired & (lengths > 0), labels)

    def _covered_thickness(self, spp: int | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(indices of the pixels that some ray crosses a particle in, their (k, spp) path lengths): the bare film
        transmits 1 exactly, so only these pixels need exp() and its gradient."""
        spp = self.spec.render.spp if spp is None else check_spp(spp, "spp")
        if spp not in self._covered:
            t = self.thickness(spp)
            index = torch.nonzero((t > 0).any(dim=1)).squeeze(1)
            self._covered[spp] = (index, t[index])
        return self._covered[spp]

    # -- rendering ------------------------------------------------------------------------------
    def transmission_values(self, values: torch.Tensor) -> dict[str, torch.Tensor]:
        """background, absorption, floor (and fringe_amplitude) as 0-d tensors: learned ones from ``values``, fixed
        ones as constants."""
        learned = iter(values)
        return {p.name: next(learned) if p.learned else values.new_tensor(p.value) for p in self.spec.parameters.bsdf}

    def render(self, values: torch.Tensor, seed: int, spp: int | None = None) -> torch.Tensor:
        """The image of the current layout: (H, W), float32 (float64 when ``values`` is), differentiable w.r.t.
        ``values`` (the learned ones of background, absorption, floor, fringe_amplitude, in ``learned`` order).

        No Monte Carlo sampling: the sub-pixel rays are the strata centres and autograd gives the exact gradient,
        so ``seed`` (`drgan.scene.protocol.Scene`) changes nothing.
        """
        del seed
        values = torch.as_tensor(values)
        dtype = torch.float64 if values.dtype == torch.float64 else torch.float32
        values = values.to(dtype)
        if values.shape != (len(self._learned),):
            raise ConfigError(
                f"values: expected shape ({len(self._learned)},) for {[p.key for p in self._learned]}, "
                f"got {tuple(values.shape)}"
            )
        size = self.spec.render.resolution
        index, t = (x.to(values.device) for x in self._covered_thickness(spp))
        v = self.transmission_values(values)
        covered = torch.exp(-v["absorption"] * t.to(dtype)).mean(dim=1)
        transmitted = torch.ones(size * size, dtype=dtype, device=values.device).index_put((index,), covered)
        transmitted = transmitted.reshape(size, size)
        image = v["floor"] + (v["background"] - v["floor"]) * transmitted
        width = self.spec.fringe_width_render_px
        if width is not None:  # the defocus fringe of the darkening (exactly 0 on bare film); blurred as the rest
            darkening = (v["background"] - v["floor"]) * (1.0 - transmitted)
            image = image + v[FRINGE_PARAMETER] * edge_fringe(darkening, width)
        return reconstruction_blur(image, self.spec.render.filter_stddev)
