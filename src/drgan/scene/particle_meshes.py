"""Particle meshes: procedural generators (spheres, deformed cubes, bent rods) and user mesh files.

Unit convention (every mesh this module returns):
    * centred at the origin: the centre of its axis-aligned bounding box is (0, 0, 0);
    * scaled so that the largest extent of its axis-aligned bounding box is exactly 1.
  The `scale` of a particle in the layout tensor Phi (x, y, z, scale) is therefore the particle's largest
  bounding-box extent in scene units (a sphere of scale s has diameter s).
  Meshes are triangle meshes with outward normals (consistent winding, positive volume) and no degenerate
  faces; generated meshes are also watertight. User files are validated but not required to be watertight.

The camera looks down the -z axis onto a stage in the x-y plane, so rods are generated lying in the x-y plane.

Only trimesh, numpy and scipy here: scene building (Mitsuba) reads these meshes, not the other way round.
"""

from __future__ import annotations

import inspect
import json
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from drgan.core.errors import ConfigError, MeshError, check_keys
from drgan.core.io import write_bytes

MESH_SUFFIXES = (".ply", ".obj", ".stl")

# Faces whose area is below this fraction of (largest bbox extent)^2 count as degenerate: they have no
# well-defined normal and break ray-triangle intersection.
_DEGENERATE_AREA_FRACTION = 1e-12


# --------------------------------------------------------------------------------------------------
# Validation and normalisation
# --------------------------------------------------------------------------------------------------


def validate_mesh(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh:
    """Check that `mesh` can be rendered; raise MeshError naming `name` and the problem. Returns `mesh`."""
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"mesh {name!r}: expected a triangle mesh (trimesh.Trimesh), got {type(mesh).__name__}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(vertices) == 0:
        raise MeshError(f"mesh {name!r} is empty (0 vertices, {len(faces)} faces); expected at least one triangle")
    if len(faces) == 0:
        raise MeshError(f"mesh {name!r}: {len(vertices)} vertices but no faces: expected a triangle mesh")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(
            f"mesh {name!r}: expected vertices of shape (V, 3) and triangle faces of shape (F, 3), "
            f"got {vertices.shape} and {faces.shape}"
        )
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise MeshError(f"mesh {name!r} has {len(bad)} non-finite vertices (NaN or inf), first at index {bad[0]}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(
            f"mesh {name!r} has face indices out of range: indices span [{faces.min()}, {faces.max()}] "
            f"but there are {len(vertices)} vertices"
        )
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    if repeated.any():
        bad = np.flatnonzero(repeated)
        raise MeshError(
            f"mesh {name!r} has {len(bad)} degenerate faces that repeat a vertex index, first is face {bad[0]}"
        )
    triangles = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    largest_extent = float(np.ptp(vertices, axis=0).max())
    zero_area = areas <= _DEGENERATE_AREA_FRACTION * largest_extent**2
    if zero_area.any():
        bad = np.flatnonzero(zero_area)
        raise MeshError(f"mesh {name!r} has {len(bad)} degenerate faces of zero area, first is face {bad[0]}")
    return mesh


def normalize_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Return a copy centred at its bbox centre and scaled so its largest bbox extent is 1 (unit convention)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    lower, upper = vertices.min(axis=0), vertices.max(axis=0)
    largest_extent = float((upper - lower).max())
    if not np.isfinite(largest_extent) or largest_extent <= 0.0:
        raise MeshError(f"cannot normalise a mesh of zero extent (bounding box {lower} to {upper})")
    normalized = (vertices - 0.5 * (lower + upper)) / largest_extent
    return trimesh.Trimesh(vertices=normalized, faces=np.asarray(mesh.faces), process=False)


def _finish(vertices: np.ndarray, faces: np.ndarray, name: str) -> trimesh.Trimesh:
    """Orient outward, normalise and validate a generated mesh."""
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if mesh.volume < 0:  # winding built inward: flip every face
        mesh.invert()
    return validate_mesh(normalize_mesh(mesh), name)


# --------------------------------------------------------------------------------------------------
# Generators
# --------------------------------------------------------------------------------------------------


def sphere(subdivisions: int = 3) -> trimesh.Trimesh:
    """Icosphere of diameter 1 (642 vertices at 3 subdivisions: 10 * 4**subdivisions + 2)."""
    if subdivisions < 0:
        raise ConfigError(f"sphere subdivisions must be >= 0, got {subdivisions}")
    icosphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return _finish(icosphere.vertices, icosphere.faces, f"sphere(subdivisions={subdivisions})")


def _cube_grid(segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Surface of the cube [-0.5, 0.5]^3 as a grid of `segments` x `segments` quads per face, split into
    right triangles of equal size, outward winding; 6 * segments**2 + 2 shared vertices."""
    ticks = np.linspace(-0.5, 0.5, segments + 1)
    u, v = np.meshgrid(ticks, ticks, indexing="ij")
    u, v = u.ravel(), v.ravel()
    row = segments + 1
    i, j = np.meshgrid(np.arange(segments), np.arange(segments), indexing="ij")
    corner = (i * row + j).ravel()
    # quad (i, j), (i+1, j), (i+1, j+1), (i, j+1), counter-clockwise in (u, v)
    quad = np.stack([corner, corner + row, corner + row + 1, corner + 1], axis=1)
    face_triangles = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])

    all_vertices, all_faces = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            # (u, v) axes chosen so that e_u x e_v points along the outward normal sign * e_axis
            u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
            if sign < 0:
                u_axis, v_axis = v_axis, u_axis
            points = np.empty((len(u), 3))
            points[:, axis] = 0.5 * sign
            points[:, u_axis] = u
            points[:, v_axis] = v
            all_faces.append(face_triangles + sum(len(p) for p in all_vertices))
            all_vertices.append(points)
    mesh = trimesh.Trimesh(np.concatenate(all_vertices), np.concatenate(all_faces), process=False)
    mesh.merge_vertices()  # weld the shared cube edges so the surface is watertight
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _bulge(rng: np.random.Generator, mesh: trimesh.Trimesh, reference: np.ndarray, amplitude: float) -> trimesh.Trimesh:
    """Move each vertex along its normal by a smooth random field: four random plane waves with wavelengths
    of one to two particle sizes, evaluated at ``reference`` (undeformed positions), of rms ~``amplitude``."""
    wave_count = 4
    wave_vectors = rng.normal(0.0, 1.0, size=(wave_count, 3))
    wave_vectors *= (2 * np.pi * rng.uniform(0.5, 1.0, size=wave_count) / np.linalg.norm(wave_vectors, axis=1))[:, None]
    phases = rng.uniform(0.0, 2 * np.pi, size=wave_count)
    amplitudes = rng.normal(0.0, amplitude / np.sqrt(wave_count), size=wave_count)
    field = (amplitudes * np.sin(reference @ wave_vectors.T + phases)).sum(axis=1)
    return trimesh.Trimesh(mesh.vertices + field[:, None] * mesh.vertex_normals, mesh.faces, process=False)


def potato(
    rng: np.random.Generator,
    middle: tuple[float, float] = (0.55, 0.95),
    short: tuple[float, float] = (0.45, 0.8),
    bulge: float = 0.06,
    tilt_deg: float = 15.0,
    subdivisions: int = 3,
) -> trimesh.Trimesh:
    """Rounded, irregular ellipsoid lying on the stage: the shape of most particles in the TiO2 SEM images
    (rounded, often elongated, no sharp faces), which neither spheres nor deformed cubes match.

    middle, short: ranges of the middle and shortest semi-axes relative to the longest (drawn uniformly;
        the shortest is also kept <= the middle). The shortest axis points up (a particle rests on its
        broad side), the long axis lies at a random heading in the stage plane.
    bulge: rms of a smooth random normal displacement (fraction of the longest axis): gently dented sides.
    tilt_deg: largest random tilt (degrees) of the resting pose about a horizontal axis.
    subdivisions: of the icosphere it starts from (642 vertices at 3).
    """
    for name, (low, high) in (("middle", middle), ("short", short)):
        if not 0 < low <= high <= 1:
            raise ConfigError(f"potato {name}={(low, high)}: expected 0 < low <= high <= 1 (fraction of the long axis)")
    if bulge < 0:
        raise ConfigError(f"potato bulge must be >= 0, got {bulge}")
    if not 0 <= tilt_deg <= 90:
        raise ConfigError(f"potato tilt_deg must be in [0, 90], got {tilt_deg}")
    ball = trimesh.creation.icosphere(subdivisions=subdivisions)
    unit = np.asarray(ball.vertices)
    b = rng.uniform(*middle)
    c = min(rng.uniform(*short), b)
    mesh = trimesh.Trimesh(unit * np.array([1.0, b, c]), ball.faces, process=False)
    mesh = _bulge(rng, mesh, unit, bulge)
    tilt_axis = np.array([*rng.normal(size=2), 0.0])
    tilt = Rotation.from_rotvec(np.radians(rng.uniform(-tilt_deg, tilt_deg)) * tilt_axis / np.linalg.norm(tilt_axis))
    heading = Rotation.from_euler("z", rng.uniform(0.0, 2 * np.pi))
    vertices = np.asarray(mesh.vertices) @ (tilt * heading).as_matrix().T
    return _finish(vertices, mesh.faces, f"potato(middle={middle}, short={short}, bulge={bulge})")


def deformed_cube(
    rng: np.random.Generator,
    displacement: float = 0.1,
    subdivisions: int = 10,
    smoothing_iterations: int = 8,
    random_orientation: bool = True,
) -> trimesh.Trimesh:
    """Irregular cube with rounded edges, like a TiO2 (anatase) nanoparticle.

    displacement: size of the random deformation as a fraction of the cube's edge length.
    subdivisions: grid segments per cube edge; 6 * subdivisions**2 + 2 vertices (602 at 10).
    smoothing_iterations: Taubin smoothing passes; more passes round edges and corners more.
    random_orientation: rotate the particle uniformly at random. The layout tensor holds no rotation, so
        without it every cube in a scene would show the camera the same face.

    The deformation is smooth across the surface (white noise per vertex would look like a rough rock):
    the 8 corners move randomly with the rest of the cube following by trilinear interpolation (skewed,
    uneven faces), then each vertex moves along its normal by a random low-frequency field (gently bulged
    or dented faces). Taubin smoothing then rounds edges without shrinking the particle.
    """
    if displacement < 0:
        raise ConfigError(f"cube displacement must be >= 0 (fraction of the edge length), got {displacement}")
    if subdivisions < 1:
        raise ConfigError(f"cube subdivisions must be >= 1 (segments per edge), got {subdivisions}")
    if smoothing_iterations < 0:
        raise ConfigError(f"cube smoothing_iterations must be >= 0, got {smoothing_iterations}")
    vertices, faces = _cube_grid(subdivisions)

    # Corner moves, trilinearly interpolated: weights of corner (cx, cy, cz) in {0, 1}^3 at each vertex.
    corner_moves = rng.normal(0.0, displacement, size=(2, 2, 2, 3))
    t = vertices + 0.5  # in [0, 1]^3
    moved = vertices.copy()
    for cx in (0, 1):
        for cy in (0, 1):
            for cz in (0, 1):
                weight = (
                    (t[:, 0] if cx else 1 - t[:, 0])
                    * (t[:, 1] if cy else 1 - t[:, 1])
                    * (t[:, 2] if cz else 1 - t[:, 2])
                )
                moved += weight[:, None] * corner_moves[cx, cy, cz]

    mesh = _bulge(rng, trimesh.Trimesh(moved, faces, process=False), vertices, 0.5 * displacement)

    if smoothing_iterations:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=smoothing_iterations)
    vertices = np.asarray(mesh.vertices)
    if random_orientation:
        vertices = vertices @ Rotation.random(random_state=rng).as_matrix().T
    return _finish(vertices, mesh.faces, f"deformed_cube(displacement={displacement})")


def bent_rod(
    rng: np.random.Generator,
    aspect: float = 10.0,
    bend: float = 0.8,
    taper: float = 0.3,
    rings: int = 32,
    segments: int = 24,
) -> trimesh.Trimesh:
    """Slender, slightly conical rod (silver nanowire) bent along a circular arc, lying in the x-y plane.

    aspect: centreline length / diameter at the thick end (> 1).
    bend: largest total turning angle of the centreline in radians; each rod draws an angle uniformly
        from [bend / 4, bend] with a random sign (0 gives a straight rod).
    taper: 1 - (radius at the thin end / radius at the thick end), in [0, 1); 0 is a cylinder.
    rings, segments: cross-sections along the rod and vertices around each; rings * segments + 2
        vertices (770 by default). Ends are closed by flat caps.

    The rod is also rotated about its own axis (the seam and facets of its cross-section land anywhere)
    and about the z axis (any direction in the x-y plane). Because the unit convention scales the
    bounding box, the rod's arc length in units of `scale` depends on that direction (1 to about 1.4).
    """
    if aspect <= 1:
        raise ConfigError(f"rod aspect (length / diameter) must be > 1, got {aspect}")
    if not 0 <= bend < 2 * np.pi:
        raise ConfigError(f"rod bend (turning angle in radians) must be in [0, 2*pi), got {bend}")
    if not 0 <= taper < 1:
        raise ConfigError(f"rod taper must be in [0, 1), got {taper}")
    if rings < 2 or segments < 3:
        raise ConfigError(f"rod needs rings >= 2 and segments >= 3, got rings={rings}, segments={segments}")

    turning = rng.uniform(0.25, 1.0) * bend * rng.choice([-1.0, 1.0])
    roll = rng.uniform(0.0, 2 * np.pi)
    heading = rng.uniform(0.0, 2 * np.pi)

    # Centreline of unit arc length in the x-y plane: a circular arc with heading angle turning * s.
    arc = np.linspace(0.0, 1.0, rings)
    angle = turning * arc
    if abs(turning) > 1e-9:
        centre = np.stack([np.sin(angle) / turning, (1 - np.cos(angle)) / turning, np.zeros(rings)], axis=1)
    else:
        centre = np.stack([arc, np.zeros(rings), np.zeros(rings)], axis=1)
    in_plane_normal = np.stack([-np.sin(angle), np.cos(angle), np.zeros(rings)], axis=1)
    up = np.array([0.0, 0.0, 1.0])

    base_radius = 0.5 / aspect
    radius = base_radius * (1 - taper * arc)
    around = roll + 2 * np.pi * np.arange(segments) / segments
    offsets = (
        np.cos(around)[None, :, None] * in_plane_normal[:, None, :] + np.sin(around)[None, :, None] * up
    )  # (rings, segments, 3)
    ring_vertices = centre[:, None, :] + radius[:, None, None] * offsets
    vertices = np.concatenate([ring_vertices.reshape(-1, 3), centre[[0, -1]]])

    ring_index = np.arange(rings - 1)[:, None] * segments
    k = np.arange(segments)[None, :]
    a, b = ring_index + k, ring_index + (k + 1) % segments
    c, d = a + segments, b + segments
    side = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    start_centre, end_centre = rings * segments, rings * segments + 1
    start_ring, end_ring = np.arange(segments), (rings - 1) * segments + np.arange(segments)
    start_cap = np.stack([np.full(segments, start_centre), np.roll(start_ring, -1), start_ring], axis=1)
    end_cap = np.stack([np.full(segments, end_centre), end_ring, np.roll(end_ring, -1)], axis=1)
    faces = np.concatenate([side, start_cap, end_cap])

    rotation = trimesh.transformations.rotation_matrix(heading, up)[:3, :3]
    return _finish(vertices @ rotation.T, faces, f"bent_rod(aspect={aspect}, bend={bend}, taper={taper})")


def _sphere_from_rng(rng: np.random.Generator, subdivisions: int = 3) -> trimesh.Trimesh:
    """Spheres need no randomness; same call shape as the other generators."""
    return sphere(subdivisions=subdivisions)


KINDS: dict[str, Callable[..., trimesh.Trimesh]] = {
    "sphere": _sphere_from_rng,
    "cube": deformed_cube,
    "rod": bent_rod,
    "potato": potato,
}


def generator_parameters(kind: str, **params) -> dict:
    """The generator's effective keyword parameters for `kind`: its defaults updated by `params`.

    Unknown kinds or parameter names raise ConfigError naming the valid ones."""
    if kind not in KINDS:
        raise ConfigError(f"unknown mesh kind {kind!r}; expected one of {sorted(KINDS)}")
    signature = inspect.signature(KINDS[kind])
    defaults = {name: p.default for name, p in signature.parameters.items() if name != "rng"}
    check_keys(f"mesh kind {kind!r}", params, sorted(defaults), "parameter")
    return {**defaults, **params}


def iter_meshes(kind: str, count: int, seed: int, **params) -> Iterator[trimesh.Trimesh]:
    """Yield `count` meshes of `kind` ('sphere', 'cube', 'rod') one at a time (for progress display).

    Checks run before the first mesh is made. Each mesh has its own random stream spawned from `seed`,
    so mesh i is the same whatever `count` is."""
    parameters = generator_parameters(kind, **params)
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ConfigError(f"mesh count must be an integer >= 1, got {count!r}")
    streams = np.random.SeedSequence(seed).spawn(int(count))
    return (KINDS[kind](np.random.default_rng(stream), **parameters) for stream in streams)


def generate_meshes(kind: str, count: int, seed: int, **params) -> list[trimesh.Trimesh]:
    """`count` meshes of `kind` ('sphere', 'cube', 'rod'); the same seed gives identical meshes."""
    return list(iter_meshes(kind, count, seed, **params))


# --------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Read a PLY, OBJ or STL file as one triangle mesh (several parts are concatenated), validated and
    normalised to the unit convention. Problems raise MeshError naming the file."""
    return validate_mesh(normalize_mesh(read_mesh(path)), str(path))


def mesh_frame(path: str | os.PathLike) -> tuple[np.ndarray, float]:
    """Where `load_mesh` moved the file's mesh from: (centre of its bounding box, its largest extent), in the file's
    own units. ``centre + extent * unit_vertices`` gives back the file's vertices."""
    vertices = np.asarray(read_mesh(path).vertices, dtype=np.float64)
    lower, upper = vertices.min(axis=0), vertices.max(axis=0)
    return 0.5 * (lower + upper), float((upper - lower).max())


def read_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """A mesh file as it is (the file's own units and origin), validated; duplicate vertices merged."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file {str(path)!r} does not exist or is not a file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshError(
            f"mesh file {str(path)!r} has unsupported suffix {path.suffix!r}; expected one of {MESH_SUFFIXES}"
        )
    try:
        # process=False: validate the file's own data before trimesh silently repairs or drops any of it
        mesh = trimesh.load(path, process=False)
        # Faceless geometry (a PLY of vertices only) loads as a point cloud, which force="mesh" would turn into an
        # empty mesh: its vertices are counted here so that the message says what the file holds.
        parts = list(mesh.geometry.values()) if isinstance(mesh, trimesh.Scene) else [mesh]
        if parts and all(isinstance(part, trimesh.PointCloud) for part in parts):
            n_vertices = sum(len(part.vertices) for part in parts)
            raise MeshError(f"mesh file {str(path)!r}: {n_vertices} vertices but no faces: expected a triangle mesh")
        if not isinstance(mesh, trimesh.Trimesh):
            mesh = trimesh.load(path, force="mesh", process=False)  # several parts: concatenated
    except MeshError:
        raise
    except Exception as error:  # trimesh raises many kinds for bad files
        raise MeshError(f"mesh file {str(path)!r} could not be read: {type(error).__name__}: {error}") from error
    if isinstance(mesh, trimesh.Scene):  # an empty scene is all force='mesh' can give back
        raise MeshError(f"mesh file {str(path)!r} contains no triangle geometry")
    validate_mesh(mesh, str(path))
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    mesh.merge_vertices()  # STL and some OBJ files store each triangle's corners separately
    return mesh


def load_mesh_set(path: str | os.PathLike) -> list[trimesh.Trimesh]:
    """Meshes from a folder (every .ply/.obj/.stl in it, sorted by file name) or from a single file."""
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
        if not files:
            raise MeshError(
                f"mesh folder {str(path)!r} contains no mesh files; expected files ending in {MESH_SUFFIXES}"
            )
        return [load_mesh(file) for file in files]
    return [load_mesh(path)]


_MESH_FILE_PATTERN = re.compile(r"mesh_\d+\.ply")


def save_mesh_set(meshes: list[trimesh.Trimesh], out_dir: str | os.PathLike, manifest: dict) -> Path:
    """Write meshes as binary PLY files out_dir/mesh_000.ply, ... and out_dir/manifest.json.

    The manifest is `manifest` plus per-file vertex and face counts. Each file is written under a temporary
    name and renamed, so a reader never sees half a file. Older mesh_NNN.ply files beyond this set are
    removed, so the folder always holds exactly this set. Returns the manifest path."""
    if not meshes:
        raise MeshError(f"no meshes to save into {str(out_dir)!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    width = max(3, len(str(len(meshes) - 1)))
    entries = []
    for index, mesh in enumerate(meshes):
        name = f"mesh_{index:0{width}d}.ply"
        validate_mesh(mesh, name)
        write_bytes(out_dir / name, trimesh.exchange.ply.export_ply(mesh, encoding="binary"))
        entries.append({"file": name, "vertices": len(mesh.vertices), "faces": len(mesh.faces)})
    written = {entry["file"] for entry in entries}
    for stale in out_dir.iterdir():
        if _MESH_FILE_PATTERN.fullmatch(stale.name) and stale.name not in written:
            stale.unlink()
    manifest_path = out_dir / "manifest.json"
    full_manifest = {**manifest, "meshes": entries}
    write_bytes(manifest_path, (json.dumps(full_manifest, indent=2) + "\n").encode())
    return manifest_path
