"""The particle scene: a stage, lights, a camera looking straight down, and n particle meshes.

Units: one scene unit is one pixel of the real image at native resolution. The camera sees the square
x, y in [-view_width/2, view_width/2] of the stage plane z = 0; ``resolution`` only sets how many pixels
the render has, so the same layout renders the same picture at 64 or 512 px.

Particles form **one merged mesh** (vertex buffer of all n meshes back to back). A layout phi_i (n x 4:
x, y, z, scale) moves them in one vectorised write of the vertex buffer, so every layout reuses the same
compiled kernels (no Python scalar is baked into them), and a ray's primitive index tells which particle it
hit, which gives exact, occlusion-correct instance labels (`instance_labels`).

`MeshParticles` holds what every drgan scene shares (merged mesh, layouts, camera, labels); `ParticleScene`
adds the secondary-electron picture below, drgan.scene.transmission.TransmissionScene the transmission one. Both
implement `drgan.scene.protocol.Scene`.

Only BSDF parameters get gradients. Uniform scaling and translation keep vertex normals' directions, and
Mitsuba recomputes them from the new positions anyway.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh

from drgan.core import backend
from drgan.core.errors import ConfigError, check_spp
from drgan.scene import direct
from drgan.scene.config import Material, SecondaryImaging, TopLight, TorusLight, register_scene
from drgan.scene.mitsuba_shapes import mitsuba_mesh, rectangle_mesh
from drgan.scene.parameters import MaterialParameters, Parameter
from drgan.scene.render_settings import DIRECT_INTEGRATORS, GRAD_SEEDS, RenderSettings
from drgan.scene.render_settings import INTEGRATORS as INTEGRATORS  # re-exported (benchmarks)

dr = backend.dr
mi = backend.mi

# RenderSettings (the renderer group, typed) and its names live in drgan.scene.render_settings, which composing a
# config reads without starting Mitsuba; they are imported here as before.


@dataclass(frozen=True)
class SceneSpec:
    parameters: MaterialParameters
    render: RenderSettings = field(default_factory=RenderSettings)
    view_width: float = 256.0  # px of the real image seen by the camera
    stage: bool = True
    torus_light: TorusLight | None = field(default_factory=TorusLight)
    top_light: TopLight | None = field(default_factory=TopLight)
    recapture: float = 0.0  # material.imaging.recapture (drgan.scene.config.SecondaryImaging)

    def __post_init__(self):
        if not self.view_width > 0:
            raise ConfigError(f"view_width={self.view_width}: expected > 0 (pixels of the real image)")
        if self.torus_light is None and self.top_light is None:
            raise ConfigError("scene has no light: enable torus_light or top_light")
        if not self.stage and self.parameters.surface("stage"):
            raise ConfigError(
                "material.imaging.stage_bsdf is configured but material.imaging.stage is false; remove one"
            )


def gaussian_kernel(sigma: float, dtype=torch.float32, device=None) -> torch.Tensor:
    """Normalised 1-D Gaussian of stddev ``sigma`` px, truncated at 4 sigma (radius at least 1): 2 radius + 1 taps."""
    radius = max(1, int(math.ceil(4.0 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    return kernel / kernel.sum()


def reconstruction_blur(image: torch.Tensor, stddev: float) -> torch.Tensor:
    """The Gaussian reconstruction filter, applied to the box-filtered render as a separable blur.

    A box-filtered pixel already averages over its own square (variance 1/12 px^2 per axis), so the
    blur uses stddev' = sqrt(stddev^2 - 1/12): the total blur then has the configured variance, as
    Mitsuba's Gaussian filter gives. Borders replicate the edge pixels. Differentiable, and cheap.
    """
    variance = stddev * stddev - 1.0 / 12.0
    if variance <= 1e-6:
        return image
    kernel = gaussian_kernel(math.sqrt(variance), image.dtype, image.device)
    radius = (len(kernel) - 1) // 2
    padded = torch.nn.functional.pad(image[None, None], (radius, radius, radius, radius), mode="replicate")
    rows = torch.nn.functional.conv2d(padded, kernel.view(1, 1, 1, -1))
    return torch.nn.functional.conv2d(rows, kernel.view(1, 1, -1, 1))[0, 0]


def torus_light_mesh(light: TorusLight, view_width: float) -> trimesh.Trimesh:
    """The emitting surface of the ring light, in scene units (px), facing the scene.

    An area light is sampled uniformly over its surface (next-event estimation in ``prb`` and
    ``direct_projective``). On a whole torus most of that surface (top, outside, far side of the tube)
    faces away from everything the camera sees, and the rest is seen at grazing angles, so the samples
    are wasted or weak and the particle pixels stay grainy: at 16 spp the particles' noise was ~0.1 grey,
    seven times the real images', and a discriminator tells images apart by that alone.

    - "band": a conical strip of revolution, centred on the tube's centre circle, of width 2 x minor
      radius, perpendicular to the line to the view centre, emitting towards it: the same ring of
      directions, nearly every sample useful (particle noise at spp 16 with prb: 0.060 vs 0.086 for the
      torus; prb_basic samples no lights and gets ~0.107 with either; experiments/benchmarks/render.md).
    - "torus": the paper's tube, minus the faces that light nothing in the scene volume. A face lights p
      only if n . (p - c) > 0 (normal n, centroid c); over the box holding every particle (view square,
      up to one view width high) that test is largest at a corner, so faces failing it at all corners are
      dropped (about 40 %): the light reaching the particles is unchanged.
    """
    w = float(view_width)
    radius, height, half_width = light.major_radius * w, light.height * w, light.minor_radius * w
    if light.shape == "band":
        # Unit vector across the strip, in the (radial, z) plane, perpendicular to the line to the origin.
        norm = math.hypot(radius, height)
        across_r, across_z = -height / norm, radius / norm
        angle = np.linspace(0.0, 2.0 * np.pi, int(light.segments), endpoint=False)
        rims = [
            np.stack([r * np.cos(angle), r * np.sin(angle), np.full_like(angle, z)], axis=1)
            for r, z in (
                (radius - half_width * across_r, height - half_width * across_z),
                (radius + half_width * across_r, height + half_width * across_z),
            )
        ]
        k = np.arange(len(angle))
        nxt, m = (k + 1) % len(angle), len(angle)
        faces = np.concatenate([np.stack([k, nxt, m + k], 1), np.stack([nxt, m + nxt, m + k], 1)])
        ring = trimesh.Trimesh(np.concatenate(rims), faces, process=False)
        away = np.einsum("fk,fk->f", ring.face_normals, -ring.triangles_center) < 0
        ring.faces[away] = ring.faces[away][:, ::-1]  # emit towards the scene
        return ring
    ring = trimesh.creation.torus(major_radius=radius, minor_radius=half_width)
    ring.apply_translation([0, 0, height])
    corners = np.array([[x, y, z] for x in (-w / 2, w / 2) for y in (-w / 2, w / 2) for z in (0.0, w)])
    facing = np.einsum("fk,cfk->cf", ring.face_normals, corners[:, None, :] - ring.triangles_center[None])
    ring.update_faces((facing > 0).any(axis=0))
    ring.remove_unreferenced_vertices()
    return ring


def _principled(parameters: Sequence[Parameter]) -> dict:
    """A Principled BSDF with fixed values set and learned ones at their mid-range (overwritten per render)."""
    bsdf = {"type": "principled"}
    for p in parameters:
        bsdf[p.name] = p.value if not p.learned else 0.5 * (p.low + p.high)
    return bsdf


def camera_sensor_dict(render: RenderSettings, view_width: float) -> dict:
    """The camera of every drgan scene: straight down from ``camera_distance`` x view width onto the view square."""
    distance = render.camera_distance * view_width
    fov = 2.0 * math.degrees(math.atan(0.5 * view_width / distance))
    return {
        "type": "perspective",
        "fov": fov,
        "fov_axis": "x",
        "near_clip": 0.5 * distance,
        "far_clip": 2.0 * distance,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, distance], target=[0, 0, 0], up=[0, 1, 0]),
        "sampler": {"type": "stratified", "sample_count": render.spp},
        "film": {
            "type": "hdrfilm",
            "width": render.resolution,
            "height": render.resolution,
            "pixel_format": "rgb",
            # Box here, Gaussian afterwards in torch (see `reconstruction_blur`): splatting every sample
            # into a (8 stddev + 1)^2 footprint made the Gaussian filter the main cost of a render
            # (stddev 3.0: 5.7 s vs 0.41 s per forward+backward at 256 px, 16 spp, 40 particles).
            "rfilter": {"type": "box"},
        },
    }


class MeshParticles:
    """What every drgan scene shares: n particle meshes merged into one Mitsuba mesh, re-posed per layout,
    the straight-down camera, and the exact instance labels traced through it.

    ``meshes`` are unit meshes (largest extent 1, centred); particle k uses ``meshes[k % len(meshes)]``.
    A subclass is a `drgan.scene.protocol.Scene`: it gives its ``Config`` (the material.imaging dataclass),
    `spec_from_config` (its spec from a material), `render` and `learned`, the rest of its Mitsuba scene
    (`_scene_dict`, which must hold ``self.particles`` under the key "particles"), the scene parameters a render
    changes (`_render_keys`) and, optionally, the particles' BSDF (`_particle_bsdf`); `_layout_changed` drops
    whatever it caches per layout.
    """

    Config: type

    @classmethod
    def from_config(cls, material: Material, render: RenderSettings, meshes: Sequence[trimesh.Trimesh], variant="auto"):
        """The scene of a typed material (`drgan.scene.config.typed_material`) with render settings ``render``."""
        return cls(meshes, material.n_particles, cls.spec_from_config(material, render), variant)

    @classmethod
    def spec_from_config(cls, material: Material, render: RenderSettings):
        raise NotImplementedError

    @property
    def learned(self) -> tuple[Parameter, ...]:
        raise NotImplementedError

    def render(self, values: torch.Tensor, seed: int, spp: int | None = None) -> torch.Tensor:
        raise NotImplementedError

    def __init__(self, meshes: Sequence[trimesh.Trimesh], n_particles: int, spec, variant: str = "auto"):
        if n_particles < 1:
            raise ConfigError(f"n_particles={n_particles}: expected >= 1")
        if not meshes:
            raise ConfigError("meshes: expected at least one particle mesh")
        self.variant = backend.use_variant(variant)
        self.spec = spec
        self.n_particles = int(n_particles)
        chosen = [meshes[k % len(meshes)] for k in range(self.n_particles)]
        self._unit_vertices = np.concatenate([m.vertices for m in chosen]).astype(np.float32)
        vertex_counts = np.array([len(m.vertices) for m in chosen])
        face_counts = np.array([len(m.faces) for m in chosen])
        self._vertex_owner = np.repeat(np.arange(self.n_particles), vertex_counts)
        vertex_offsets = np.concatenate([[0], np.cumsum(vertex_counts)[:-1]])
        faces = np.concatenate([m.faces + off for m, off in zip(chosen, vertex_offsets)])
        # Face f belongs to particle face_owner[f]; +1 because label 0 is the background.
        self._face_label = mi.UInt32(np.repeat(np.arange(1, self.n_particles + 1), face_counts).astype(np.uint32))

        self.particles = mitsuba_mesh("particles", self._unit_vertices, faces)
        bsdf = self._particle_bsdf()
        if bsdf is not None:
            self.particles.set_bsdf(mi.load_dict(bsdf))
        self.scene = mi.load_dict(self._scene_dict())
        self.params = mi.traverse(self.scene)
        # Keep only what a render changes; everything else stays as loaded.
        self.params.keep(list(self._render_keys()) + ["particles.vertex_positions"])
        self._layout = None
        self._labels = None  # instance labels of the current layout, traced once per layout

    # -- hooks ----------------------------------------------------------------------------------
    def _particle_bsdf(self) -> dict | None:
        return None

    def _scene_dict(self) -> dict:
        raise NotImplementedError

    def _render_keys(self) -> Sequence[str]:
        return ()

    def _layout_changed(self) -> None:
        pass

    def _sensor_dict(self) -> dict:
        return camera_sensor_dict(self.spec.render, self.spec.view_width)

    # -- state ----------------------------------------------------------------------------------
    def set_layout(self, phi_i) -> None:
        """Move the particles to one constellation phi_i (n x 4: x, y, z, scale) in one buffer write.

        An all-zero row is an absent particle (``sample_layouts(n_min=...)``): its mesh collapses to one
        point below the stage, where its zero-area triangles can neither be hit nor cast a shadow.
        """
        phi_i = np.asarray(phi_i.detach().cpu() if isinstance(phi_i, torch.Tensor) else phi_i, dtype=np.float32)
        if phi_i.shape != (self.n_particles, 4):
            raise ConfigError(f"phi_i: expected shape ({self.n_particles}, 4) (x, y, z, scale), got {phi_i.shape}")
        if not np.isfinite(phi_i).all():
            raise ConfigError("phi_i: contains non-finite values")
        absent = ~phi_i.any(axis=1)
        if (phi_i[~absent, 3] <= 0).any():
            raise ConfigError("phi_i: particle scales (column 3) must be > 0 (an absent particle is an all-zero row)")
        placed = phi_i.copy()
        placed[absent] = (0.0, 0.0, -self.spec.view_width, 0.0)
        per_vertex = placed[self._vertex_owner]
        vertices = self._unit_vertices * per_vertex[:, 3:4] + per_vertex[:, :3]
        self.params["particles.vertex_positions"] = mi.Float(vertices.ravel())
        self.params.update()
        self._layout = phi_i
        self._labels = None
        self._layout_changed()

    @property
    def layout(self) -> np.ndarray | None:
        return self._layout

    # -- tracing --------------------------------------------------------------------------------
    def camera_rays(self, offsets) -> tuple:
        """Rays of the scene's camera through every pixel, at sub-pixel ``offsets`` ((k, 2) numbers in [0, 1)).

        Returns (rays, k): ray i * k + j passes pixel i (row-major, as the render's rows and columns) at
        offset j. Build them under ``dr.suspend_grad()``.
        """
        size = self.spec.render.resolution
        offsets = np.asarray(offsets, dtype=np.float32).reshape(-1, 2)
        k = len(offsets)
        idx = dr.arange(mi.UInt32, size * size * k)
        pixel, sub = idx // k, idx % k
        row, col = pixel // size, pixel % size
        dx = dr.gather(mi.Float, mi.Float(offsets[:, 0]), sub)
        dy = dr.gather(mi.Float, mi.Float(offsets[:, 1]), sub)
        position = mi.Point2f((mi.Float(col) + dx) / size, (mi.Float(row) + dy) / size)
        sensor = self.scene.sensors()[0]
        ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5, 0.5))
        return ray, k

    def instance_labels(self) -> np.ndarray:
        """Instance label image of the current layout (0 background, k = particle k), pixel-aligned.

        One ray through each pixel centre of the same camera: occlusion-correct and far cheaper than
        a second high-spp render. Traced once per layout (a textured render needs the stage mask, and the
        sample then needs the labels); each call returns its own copy.
        """
        if self._layout is None:
            raise RuntimeError("set_layout(phi_i) before instance_labels()")
        if self._labels is None:
            self._labels = self._trace_labels()
        return self._labels.copy()

    def _trace_labels(self) -> np.ndarray:
        size = self.spec.render.resolution
        with dr.suspend_grad():
            ray, _ = self.camera_rays([(0.5, 0.5)])
            si = self.scene.ray_intersect(ray)
            hit = si.is_valid() & (si.shape == mi.ShapePtr(self.particles))
            labels = dr.select(hit, dr.gather(mi.UInt32, self._face_label, si.prim_index, hit), 0)
            return np.asarray(labels, dtype=np.int32).reshape(size, size)


@register_scene
class ParticleScene(MeshParticles):
    """A Mitsuba scene of n particles, re-posed per layout and rendered differentiably from torch.

    Secondary-electron contrast: Principled BSDFs on particles and stage, a ring light and a top light,
    rendered by a Mitsuba integrator. ``meshes`` are unit meshes (largest extent 1, centred); particle k
    uses ``meshes[k % len(meshes)]``.
    """

    Config = SecondaryImaging

    @classmethod
    def spec_from_config(cls, material: Material, render: RenderSettings) -> SceneSpec:
        imaging: SecondaryImaging = material.imaging
        return SceneSpec(
            parameters=imaging.material_parameters(material.noise_sigma),
            render=render,
            view_width=float(material.view_width),
            stage=imaging.stage,
            torus_light=imaging.torus_light,
            top_light=imaging.top_light,
            recapture=float(imaging.recapture),
        )

    def __init__(self, meshes: Sequence[trimesh.Trimesh], n_particles: int, spec: SceneSpec, variant: str = "auto"):
        self._learned = spec.parameters.learned_bsdf
        self._learned_keys = [self._bsdf_key(p) for p in self._learned]
        super().__init__(meshes, n_particles, spec, variant)

    # -- building -------------------------------------------------------------------------------
    def _particle_bsdf(self) -> dict:
        return _principled(self.spec.parameters.surface("particle"))

    def _render_keys(self) -> list[str]:
        return self._learned_keys

    def _integrator_dict(self) -> dict:
        r = self.spec.render
        recapture = float(self.spec.recapture)  # SceneSpec and OfficialSpec carry it
        if recapture > 0 and r.integrator not in DIRECT_INTEGRATORS:
            raise ConfigError(
                f"material.imaging.recapture={recapture:g} needs renderer.integrator=direct_light or direct_light_mis "
                f"(drgan.scene.direct); renderer.integrator={r.integrator}"
            )
        if r.integrator == "direct_projective":
            # Only BSDF parameters are differentiated: no silhouette (projective) samples are needed.
            return {"type": "direct_projective", "sppp": 0, "sppi": 0}
        if r.integrator in DIRECT_INTEGRATORS:
            shapes = "*" if r.integrator == "direct_light_mis" else self._bsdf_sampled_shapes()
            out = {"type": direct.register(), "max_depth": r.max_depth, "bsdf_sampling": shapes}
            return {**out, "recapture": recapture} if recapture > 0 else out
        return {"type": r.integrator, "max_depth": r.max_depth}

    def _bsdf_sampled_shapes(self) -> str:
        """Shapes on which ``direct_light`` samples the BSDF as well as the lights (MIS).

        The particles' roughness is learned down to near-mirror lobes, where light sampling alone would
        catch a highlight rarely and with a huge weight. A stage of fixed roughness >= 0.3 (Principled
        default 0.5) is lit well by light sampling alone, which saves one ray per stage sample.
        """
        stage = {p.name: p for p in self.spec.parameters.surface("stage")}
        roughness = stage.get("roughness")
        if self.spec.stage and roughness is not None and (roughness.learned or roughness.value < 0.3):
            return "particles,stage"
        return "particles"

    def _scene_dict(self) -> dict:
        spec, w = self.spec, self.spec.view_width
        scene = {
            "type": "scene",
            "integrator": self._integrator_dict(),
            "sensor": self._sensor_dict(),
            "particles": self.particles,
        }
        if spec.stage:
            # Far larger than the view so its edge never shows, even through perspective at the border.
            props = mi.Properties()
            props["bsdf"] = mi.load_dict(_principled(spec.parameters.surface("stage")))
            scene["stage"] = rectangle_mesh("stage", mi.ScalarTransform4f().scale([4 * w, 4 * w, 1]), props)
        if spec.torus_light is not None and spec.torus_light.radiance > 0:
            t = spec.torus_light
            ring = torus_light_mesh(t, w)
            props = mi.Properties()
            props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "uniform", "value": t.radiance}})
            scene["torus_light"] = mitsuba_mesh("torus_light", ring.vertices, ring.faces, props, normals=False)
        if spec.top_light is not None and spec.top_light.radiance > 0:
            t = spec.top_light
            distance = spec.render.camera_distance * w
            props = mi.Properties()
            props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "uniform", "value": t.radiance}})
            # The rectangle emits along its local +z; flip it to face the stage.
            to_world = (
                mi.ScalarTransform4f()
                .translate([0, 0, t.height * distance])
                .rotate([1, 0, 0], 180)
                .scale([t.size * distance, t.size * distance, 1])
            )
            scene["top_light"] = rectangle_mesh("top_light", to_world, props)
        return scene

    @staticmethod
    def _bsdf_key(p: Parameter) -> str:
        owner = "particles.bsdf" if p.surface == "particle" else "stage.bsdf"
        return f"{owner}.{p.name}.value"

    # -- state ----------------------------------------------------------------------------------
    @property
    def learned(self) -> tuple[Parameter, ...]:
        """The learned BSDF parameters: the stage's, then the particles' (the material's order)."""
        return self._learned

    # -- rendering ------------------------------------------------------------------------------
    def _assign(self, values: torch.Tensor, grad: bool) -> list:
        """Write learned values into the scene (as Dr.Jit arrays: no Python float is baked into kernels)."""
        variables = []
        for key, value in zip(self._learned_keys, values.detach().cpu().tolist()):
            variable = dr.opaque(mi.Float, value, 1)
            if grad:
                dr.enable_grad(variable)
            self.params[key] = variable
            variables.append(variable)
        self.params.update()
        return variables

    def render(
        self, values: torch.Tensor, seed: int, spp: int | None = None, grad_spp: int | None = None
    ) -> torch.Tensor:
        """Render the current layout; ``values`` holds the learned BSDF parameters in ``learned`` order.

        Returns linear radiance (H x W, float32; not clamped), differentiable w.r.t. ``values``.
        ``seed`` must change between calls, or every step reuses one sample pattern.
        ``spp`` / ``grad_spp``: samples per pixel of the image and of its adjoint pass (None: the scene's
        ``renderer.spp`` / ``renderer.grad_spp``, the latter defaulting to, and capped at, the image's spp). The
        adjoint pass (Mitsuba's ``render_backward``) traces paths of its own, so a lower ``grad_spp`` keeps the
        gradient unbiased for the image's expectation and only adds variance, at a fraction of the cost of the
        backward pass (the larger half of a training step at spp 121).
        """
        if self._layout is None:
            raise RuntimeError("set_layout(phi_i) before render()")
        spp = check_spp(spp, "spp") if spp is not None else self.spec.render.spp
        if grad_spp is None:
            grad_spp = self.spec.render.grad_spp if self.spec.render.grad_spp is not None else spp
        grad_spp = min(check_spp(grad_spp, "grad_spp"), spp)  # never more adjoint samples than image samples
        values = torch.as_tensor(values, dtype=torch.float32)
        if values.shape != (len(self._learned),):
            raise ConfigError(
                f"values: expected shape ({len(self._learned)},) for {self._learned_keys}, got {tuple(values.shape)}"
            )
        image = _RenderFunction.apply(values, self, int(seed) & 0xFFFFFFFF, spp, grad_spp)
        grey = image.mean(dim=-1)  # grey lights and grey BSDFs: R = G = B
        return reconstruction_blur(grey, self.spec.render.filter_stddev)


def adjoint_seed(seed: int, grad_seed: str) -> int:
    """The seed of the adjoint pass for an image rendered with ``seed`` (32-bit), per ``renderer.grad_seed``.

    "same" returns ``seed``. "independent" returns a fixed mix of it: xor with the golden-ratio constant
    0x9E3779B9, then MurmurHash3's 32-bit finaliser (a bijection that scatters neighbouring seeds, so the
    adjoint seed of step k is not the image seed of step k + 1 as a plain offset would make it); in the rare
    case that the result equals ``seed``, its lowest bit is flipped. Deterministic, and never equal to ``seed``.
    """
    seed = int(seed) & 0xFFFFFFFF
    if grad_seed == "same":
        return seed
    if grad_seed != "independent":
        raise ConfigError(f"renderer.grad_seed={grad_seed!r}: expected one of {', '.join(GRAD_SEEDS)}")
    h = seed ^ 0x9E3779B9
    h = ((h ^ (h >> 16)) * 0x85EBCA6B) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 0xC2B2AE35) & 0xFFFFFFFF
    h ^= h >> 16
    return h ^ 1 if h == seed else h


class _RenderFunction(torch.autograd.Function):
    """torch <-> Dr.Jit bridge that stays correct when several renders precede one backward pass.

    Forward renders the primal image without an AD graph. Backward restores the layout and parameter
    values of *this* render and runs Mitsuba's adjoint pass (``render_backward``) with ``grad_spp`` samples
    and the seed that ``renderer.grad_seed`` names (`adjoint_seed`): the image's own ("same", which replays
    its samples) or one derived from it ("independent"). A plain ``dr.wrap`` around ``mi.render`` would
    replay every render's adjoint with the scene state of the *last* forward call, which silently breaks
    batches and accumulation.
    """

    @staticmethod
    def forward(ctx, values: torch.Tensor, scene: ParticleScene, seed: int, spp: int, grad_spp: int) -> torch.Tensor:
        with dr.suspend_grad():
            scene._assign(values, grad=False)
            image = mi.render(scene.scene, scene.params, seed=seed, spp=spp)
            out = torch.from_numpy(np.array(image, dtype=np.float32, copy=True))
        ctx.scene, ctx.grad_spp = scene, grad_spp
        ctx.grad_seed = adjoint_seed(
            seed, scene.spec.render.grad_seed
        )  # fixed now: a later spec change cannot alter it
        ctx.layout = scene.layout.copy()
        ctx.save_for_backward(values)
        return out.to(values.device)

    @staticmethod
    def backward(ctx, grad_image: torch.Tensor):
        scene = ctx.scene
        (values,) = ctx.saved_tensors
        if values.numel() == 0:
            return None, None, None, None, None
        if scene.layout is None or not np.array_equal(scene.layout, ctx.layout):
            scene.set_layout(ctx.layout)
        variables = scene._assign(values, grad=True)
        grad_in = mi.TensorXf(np.ascontiguousarray(grad_image.detach().cpu().numpy(), dtype=np.float32))
        scene.scene.integrator().render_backward(
            scene.scene, scene.params, grad_in, seed=ctx.grad_seed, spp=ctx.grad_spp
        )
        grads = torch.tensor([float(dr.grad(v)[0]) for v in variables], dtype=values.dtype, device=values.device)
        for v in variables:
            dr.disable_grad(v)
        return grads, None, None, None, None
