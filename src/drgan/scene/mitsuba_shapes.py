"""Mitsuba meshes from vertex and face arrays: the one way drgan's scenes and integrators build shapes."""

from __future__ import annotations

import numpy as np

from drgan.core import backend

mi = backend.mi


def mitsuba_mesh(name: str, vertices: np.ndarray, faces: np.ndarray, props=None, normals: bool = True):
    """A Mitsuba mesh of ``vertices`` (n x 3) and ``faces`` (m x 3), with ``props`` (a BSDF, an emitter)."""
    mesh = mi.Mesh(name, len(vertices), len(faces), props=props or mi.Properties(), has_vertex_normals=normals)
    buffers = mi.traverse(mesh)
    buffers["vertex_positions"] = mi.Float(np.ascontiguousarray(vertices, dtype=np.float32).ravel())
    buffers["faces"] = mi.UInt32(np.ascontiguousarray(faces, dtype=np.uint32).ravel())
    buffers.update()
    return mesh


def rectangle_mesh(name: str, to_world, props=None):
    """Mitsuba's ``rectangle`` ([-1, 1]^2 in its local xy plane, facing local +z, placed by ``to_world``) as two
    triangles.

    The same surface (rays hit it at the same t with the same normal). Mitsuba 3.9's ``rectangle`` is itself two
    triangles to Embree but keeps its own code for surface interactions and sampling, so the render kernel's calls
    over shapes run two implementations; as plain meshes every shape of drgan's scenes runs one. Measured: a render
    of the TiO2 SEM scene at spp 16 costs ~10 % less CPU time (primal and adjoint; ``benchmarks/render_parts.py``,
    experiments/benchmarks/train_step.md). The image's expectation is unchanged; an emitter on it samples its points
    through the triangles (uniform over the area, as the rectangle), so the same seed places them elsewhere. No
    UVs: the BSDFs on these surfaces are untextured.
    """
    corners = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    matrix = np.array(to_world.matrix, dtype=np.float64)
    vertices = corners @ matrix[:3, :3].T + matrix[:3, 3]
    return mitsuba_mesh(name, vertices, np.array([[0, 1, 2], [0, 2, 3]]), props, normals=False)
