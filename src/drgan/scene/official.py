"""The official DiffRenderGAN scene, for generators imported from the official code (`drgan.import_official`).

The paper's authors trained their generators in this scene, so an imported generator renders what it learned only
here: a perspective camera (40 degrees across) 6 units above the plane of the particles, looking straight down;
the official stage mesh (a slab whose top lies 3 units below that plane); a ring light around the scene
(``light_source.ply``, a torus stretched into a band 15 units out and 12.4 units up and down) and a weak light
above the camera (``light_source2.ply``); Mitsuba's ``direct_projective`` integrator (``renderer.integrator``) and a
Gaussian reconstruction filter (``material.filter_stddev``). Lengths are the official scene's units (the camera's
view is 4.37 units wide at the particles' plane: 58.6 px per unit there), y up, as in its XML.

A constellation row is (x, y, z, r) in the official layout units (`drgan.scene.placements.OfficialPlacement`): the
particle is its file mesh scaled by r x mesh_scale^2 about the file's origin and moved to (x, z, y) x mesh_unit.
The square is the official code's: its shapes load with ``to_world = scale(mesh_scale)`` and every layout then
scales the loaded vertices by r x mesh_scale again.

The learned values go where the official generator puts them (stage first, then particles, in the material's
order); the fixed values are what the official scene holds, which `drgan.import_official` works out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import trimesh

from drgan.core import backend
from drgan.core.errors import ConfigError
from drgan.scene.config import Material, OfficialImaging, register_scene
from drgan.scene.parameters import MaterialParameters
from drgan.scene.scene import ParticleScene, RenderSettings

mi = backend.mi

# The official sensor: fov 40 degrees along x, at (0, 6, 0), turned to look down -y (its XML: rotate x 90, then
# y 270, then translate).
CAMERA_FOV = 40.0
CAMERA_HEIGHT = 6.0


@dataclass(frozen=True)
class OfficialSpec:
    parameters: MaterialParameters
    imaging: OfficialImaging
    render: RenderSettings = field(default_factory=RenderSettings)
    view_width: float = 256.0  # px of the image; the network's input is divided by it (drgan.models.generator)
    stage: bool = True

    @property
    def recapture(self) -> float:
        return float(self.imaging.recapture)


def _transform(*steps):
    """A Mitsuba transform from the steps of an official XML ``<transform>`` in their order (each applies after
    the previous): ("rotate", axis, degrees), ("translate", v), ("scale", v)."""
    matrix = mi.ScalarTransform4f()
    for step in reversed(steps):
        kind, *args = step
        matrix = matrix.rotate(*args) if kind == "rotate" else getattr(matrix, kind)(*args)
    return matrix


@register_scene
class OfficialScene(ParticleScene):
    """The official DiffRenderGAN scene (module docstring), with drgan's merged particle mesh and exact labels."""

    Config = OfficialImaging

    @classmethod
    def spec_from_config(cls, material: Material, render: RenderSettings) -> OfficialSpec:
        imaging: OfficialImaging = material.imaging
        return OfficialSpec(
            parameters=imaging.material_parameters(material.noise_sigma),
            imaging=imaging,
            render=render,
            view_width=float(material.view_width),
        )

    def __init__(self, meshes: Sequence[trimesh.Trimesh], n_particles: int, spec: OfficialSpec, variant="auto"):
        frames = np.asarray(spec.imaging.mesh_frames, dtype=np.float64).reshape(-1, 4)
        if len(frames) != len(meshes):
            raise ConfigError(
                f"material.imaging.mesh_frames: {len(frames)} frames for {len(meshes)} meshes in material.meshes.dir; "
                "expected one per mesh file (run drgan.import_official again)"
            )
        super().__init__(meshes, n_particles, spec, variant)
        # Each vertex as its file holds it: centre + extent x unit vertex (the loader centred and scaled it).
        per_particle = frames[np.arange(self.n_particles) % len(frames)]
        owner = per_particle[self._vertex_owner]
        self._file_vertices = owner[:, :3] + owner[:, 3:4] * self._unit_vertices.astype(np.float64)

    def _sensor_dict(self) -> dict:
        render = self.spec.render
        return {
            "type": "perspective",
            "fov": CAMERA_FOV,
            "fov_axis": "x",
            "near_clip": 0.1,
            "far_clip": 100.0,
            "to_world": _transform(
                ("rotate", [1, 0, 0], 90), ("rotate", [0, 1, 0], 270), ("translate", [0, CAMERA_HEIGHT, 0])
            ),
            "sampler": {"type": "stratified", "sample_count": render.spp},
            "film": {
                "type": "hdrfilm",
                "width": render.resolution,
                "height": render.resolution,
                "pixel_format": "rgb",
                "rfilter": {"type": "box"},  # the Gaussian follows in torch (drgan.scene.scene.reconstruction_blur)
            },
        }

    def _scene_dict(self) -> dict:
        imaging: OfficialImaging = self.spec.imaging
        stage_props = {"type": "principled"}
        for p in self.spec.parameters.surface("stage"):
            stage_props[p.name] = p.value if not p.learned else 0.5 * (p.low + p.high)
        scene = {
            "type": "scene",
            "integrator": self._integrator_dict(),
            "sensor": self._sensor_dict(),
            "particles": self.particles,
            "stage": {
                "type": "ply",
                "filename": imaging.stage_mesh,
                "to_world": _transform(("translate", [0, -4, 0]), ("scale", [10, 1, 10])),
                "bsdf": stage_props,
            },
        }
        lights = (
            ("ring_light", imaging.ring_light_mesh, imaging.ring_radiance,
             _transform(("rotate", [1, 0, 0], -90), ("scale", [15, 200, 15]))),
            ("top_light", imaging.top_light_mesh, imaging.top_radiance,
             _transform(("rotate", [1, 0, 0], -180), ("translate", [0, 8, 0]), ("scale", [10, 1, 10]))),
        )  # fmt: skip
        for name, filename, radiance, to_world in lights:
            scene[name] = {
                "type": "ply",
                "filename": filename,
                "to_world": to_world,
                "emitter": {"type": "area", "radiance": {"type": "uniform", "value": float(radiance)}},
            }
        return scene

    def set_layout(self, phi_i) -> None:
        """Pose the particles as constellation phi_i (n x 4: x, y, z, r in layout units), in one buffer write."""
        import torch

        phi_i = np.asarray(phi_i.detach().cpu() if isinstance(phi_i, torch.Tensor) else phi_i, dtype=np.float32)
        if phi_i.shape != (self.n_particles, 4):
            raise ConfigError(f"phi_i: expected shape ({self.n_particles}, 4) (x, y, z, r), got {phi_i.shape}")
        if not np.isfinite(phi_i).all():
            raise ConfigError("phi_i: contains non-finite values")
        imaging: OfficialImaging = self.spec.imaging
        row = phi_i.astype(np.float64)
        scale = row[:, 3] * imaging.mesh_scale**2
        offset = row[:, [0, 2, 1]] * imaging.mesh_unit  # the official translate(x, z, y): z is up
        owner = self._vertex_owner
        vertices = self._file_vertices * scale[owner, None] + offset[owner]
        self.params["particles.vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
        self.params.update()
        self._layout = phi_i
        self._labels = None
        self._layout_changed()
