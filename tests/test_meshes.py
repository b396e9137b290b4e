"""Mesh generators, the unit convention, mesh files and the mesh library CLI."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from drgan.core.errors import ConfigError, MeshError
from drgan.scene.particle_meshes import (
    KINDS,
    bent_rod,
    deformed_cube,
    generate_meshes,
    load_mesh,
    load_mesh_set,
    normalize_mesh,
    save_mesh_set,
    sphere,
    validate_mesh,
)

# vertex budget per mesh: render cost scales with it and a scene holds up to 40 meshes
VERTEX_BUDGET = (500, 1500)


@pytest.fixture(scope="module")
def generated() -> dict[str, list[trimesh.Trimesh]]:
    return {kind: generate_meshes(kind, 4, seed=0) for kind in KINDS}


def assert_unit_convention(mesh: trimesh.Trimesh) -> None:
    lower, upper = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    np.testing.assert_allclose(0.5 * (lower + upper), 0.0, atol=1e-9)
    assert abs((upper - lower).max() - 1.0) < 1e-6


def centreline_deviation(mesh: trimesh.Trimesh, bins: int = 12) -> float:
    """Largest distance of cross-section centroids from the rod's principal axis (0 for a straight rod)."""
    centred = mesh.vertices - mesh.vertices.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    along = centred @ axis
    edges = np.linspace(along.min(), along.max(), bins + 1)
    which = np.clip(np.digitize(along, edges) - 1, 0, bins - 1)
    centroids = np.array([centred[which == b].mean(axis=0) for b in range(1, bins - 1)])  # skip the caps
    off_axis = centroids - np.outer(centroids @ axis, axis)
    return float(np.linalg.norm(off_axis, axis=1).max())


# --- generators -------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_generated_meshes_are_valid_closed_outward_and_unit_sized(generated, kind):
    for mesh in generated[kind]:
        validate_mesh(mesh, kind)
        assert mesh.is_watertight
        assert mesh.is_winding_consistent
        assert mesh.volume > 0  # outward normals
        assert_unit_convention(mesh)
        assert VERTEX_BUDGET[0] <= len(mesh.vertices) <= VERTEX_BUDGET[1]


def test_sphere_is_a_642_vertex_icosphere_of_diameter_one():
    mesh = sphere()
    assert len(mesh.vertices) == 642
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert radii.max() - radii.min() < 0.01
    assert abs(radii.mean() - 0.5) < 0.01


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_same_seed_gives_identical_meshes_and_count_does_not_change_earlier_ones(kind):
    first, second = generate_meshes(kind, 3, seed=7), generate_meshes(kind, 5, seed=7)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)


@pytest.mark.parametrize("kind", ["cube", "rod", "potato"])
def test_different_seeds_give_different_meshes(kind):
    (a,), (b,) = generate_meshes(kind, 1, seed=1), generate_meshes(kind, 1, seed=2)
    assert not np.allclose(a.vertices, b.vertices, atol=1e-3)


def test_deformed_cubes_deviate_from_a_perfect_cube_and_from_each_other(generated):
    def unrotated_cube(seed, **params):
        return deformed_cube(np.random.default_rng(seed), random_orientation=False, **params)

    # distance of each vertex from the centre in the max-norm: constant 0.5 on a perfect axis-aligned cube
    perfect = unrotated_cube(0, displacement=0.0, smoothing_iterations=0)
    np.testing.assert_allclose(np.abs(perfect.vertices).max(axis=1), 0.5, atol=1e-9)  # control
    for seed in range(3):
        deformed = unrotated_cube(seed)
        assert np.abs(deformed.vertices).max(axis=1).std() > 0.01
        assert deformed.volume < 0.9  # a perfect unit cube has volume 1: ours is irregular and rounded
    cubes = generated["cube"]
    assert np.ptp([cube.volume for cube in cubes]) > 0.01
    for i in range(len(cubes)):
        for j in range(i + 1, len(cubes)):
            assert not np.allclose(cubes[i].vertices, cubes[j].vertices, atol=1e-2)


def test_rods_are_elongated_bent_and_lie_flat(generated):
    for rod in generated["rod"]:
        extents = np.sort(rod.extents)
        singular_values = np.linalg.svd(rod.vertices - rod.vertices.mean(axis=0), compute_uv=False)
        assert singular_values[0] / singular_values[1] > 3  # elongated
        assert extents[0] == pytest.approx(rod.extents[2])  # thinnest along z: lying in the x-y plane
        assert centreline_deviation(rod) > 0.01
    straight = bent_rod(np.random.default_rng(0), bend=0.0)
    assert centreline_deviation(straight) < 1e-3  # control: the deviation measure sees no bend here


def test_potatoes_are_rounded_varied_and_rest_on_their_broad_side(generated):
    potatoes = generated["potato"]
    for potato in potatoes:
        extents = potato.extents
        assert extents[2] < min(extents[0], extents[1])  # thinnest vertically: resting on the broad side
        assert potato.is_convex or potato.volume > 0.8 * potato.convex_hull.volume  # no deep dents
        # rounded: no flat faces, so face normals spread smoothly (a cube's cluster around 6 directions)
        normals = potato.face_normals
        assert np.abs(normals @ normals.T).mean() < 0.6
    shapes = np.array([np.sort(p.extents) for p in potatoes])
    assert np.ptp(shapes[:, 0]) > 0.03  # varied aspect ratios, not one ellipsoid
    with pytest.raises(ConfigError, match="middle"):
        generate_meshes("potato", 1, seed=0, middle=(0.9, 0.5))


def test_generate_meshes_rejects_unknown_kind_bad_count_and_unknown_parameter():
    with pytest.raises(ConfigError, match=r"'pyramid'.*\['cube', 'potato', 'rod', 'sphere'\]"):
        generate_meshes("pyramid", 2, seed=0)
    with pytest.raises(ConfigError, match="count"):
        generate_meshes("cube", 0, seed=0)
    with pytest.raises(ConfigError, match="wobble"):
        generate_meshes("cube", 1, seed=0, wobble=1.0)


def test_normalize_mesh_centres_and_scales_and_rejects_zero_extent():
    box = trimesh.creation.box(extents=(4.0, 2.0, 1.0))
    box.apply_translation((10.0, -3.0, 5.0))
    normalized = normalize_mesh(box)
    assert_unit_convention(normalized)
    np.testing.assert_allclose(normalized.extents, (1.0, 0.5, 0.25))
    flat = trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False)
    with pytest.raises(MeshError, match="zero extent"):
        normalize_mesh(flat)


# --- files ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl"])
def test_load_mesh_roundtrip(tmp_path, generated, suffix):
    original = generated["cube"][0]
    path = tmp_path / f"particle{suffix}"
    original.export(path)
    loaded = load_mesh(path)
    assert len(loaded.vertices) == len(original.vertices)
    assert len(loaded.faces) == len(original.faces)
    assert loaded.is_watertight and loaded.volume > 0
    assert_unit_convention(loaded)
    assert loaded.volume == pytest.approx(original.volume, rel=1e-4)
    # same points, whatever order the format kept them in (PLY stores float32)
    assert np.abs(np.sort(loaded.vertices, axis=0) - np.sort(original.vertices, axis=0)).max() < 1e-5


def test_load_mesh_normalises_and_concatenates_a_multi_part_file(tmp_path):
    parts = trimesh.util.concatenate(
        [trimesh.creation.box(extents=(2, 2, 2)), trimesh.creation.box(extents=(2, 2, 2)).apply_translation((5, 0, 0))]
    )
    scene = trimesh.Scene(
        {
            "a": trimesh.creation.box(extents=(2, 2, 2)),
            "b": trimesh.creation.box(extents=(2, 2, 2)).apply_translation((5, 0, 0)),
        }
    )
    path = tmp_path / "two.obj"
    scene.export(path)
    loaded = load_mesh(path)
    assert len(loaded.faces) == len(parts.faces)
    np.testing.assert_allclose(loaded.extents, (1.0, 2 / 7, 2 / 7), atol=1e-6)


def test_save_mesh_set_writes_plys_and_manifest_and_loads_back(tmp_path, generated):
    rods = generated["rod"]
    (tmp_path / "mesh_009.ply").write_bytes(b"stale")  # left from a larger earlier set
    manifest_path = save_mesh_set(rods, tmp_path, {"kind": "rod"})
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["manifest.json", "mesh_000.ply", "mesh_001.ply", "mesh_002.ply", "mesh_003.ply"]
    manifest = json.loads(manifest_path.read_text())
    assert manifest["kind"] == "rod"
    assert [m["vertices"] for m in manifest["meshes"]] == [len(r.vertices) for r in rods]
    loaded = load_mesh_set(tmp_path)
    assert len(loaded) == len(rods)
    for a, b in zip(loaded, rods):
        np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-6)
        np.testing.assert_array_equal(a.faces, b.faces)
    assert len(load_mesh_set(tmp_path / "mesh_002.ply")) == 1


def _ascii_ply(path: Path, vertices: list, faces: list) -> Path:
    lines = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(vertices)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    lines += [" ".join(str(c) for c in v) for v in vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


TETRAHEDRON = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
TETRAHEDRON_FACES = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]


def test_a_good_ascii_ply_loads(tmp_path):
    mesh = load_mesh(_ascii_ply(tmp_path / "tetra.ply", TETRAHEDRON, TETRAHEDRON_FACES))
    assert mesh.is_watertight and mesh.volume > 0


@pytest.mark.parametrize(
    "name, vertices, faces, problem",
    [
        ("nan.ply", [[0, 0, 0], [1, 0, 0], [0, "nan", 0], [0, 0, 1]], TETRAHEDRON_FACES, "non-finite"),
        ("flat.ply", [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 1, 2], [0, 1, 3]], "zero area"),
        ("repeat.ply", TETRAHEDRON, [[0, 0, 1], [0, 1, 3]], "repeat"),
        ("range.ply", TETRAHEDRON, [[0, 1, 2], [0, 1, 9]], "out of range"),
    ],
)
def test_bad_ply_files_raise_mesh_error_naming_the_file(tmp_path, name, vertices, faces, problem):
    path = _ascii_ply(tmp_path / name, vertices, faces)
    with pytest.raises(MeshError, match=problem) as caught:
        load_mesh(path)
    assert name in str(caught.value)


def test_ply_of_vertices_without_faces_reports_its_vertices(tmp_path):
    with_empty_faces = _ascii_ply(tmp_path / "points.ply", TETRAHEDRON, [])  # "element face 0"
    no_face_element = tmp_path / "cloud.ply"
    header = [
        "ply",
        "format ascii 1.0",
        "element vertex 4",
        "property float x",
        "property float y",
        "property float z",
        "end_header",
    ]
    no_face_element.write_text("\n".join([*header, *(" ".join(map(str, v)) for v in TETRAHEDRON)]) + "\n")
    for path in (with_empty_faces, no_face_element):
        with pytest.raises(MeshError, match=rf"{path.name}'?: 4 vertices but no faces: expected a triangle mesh"):
            load_mesh(path)
    with pytest.raises(MeshError, match="'cube': 4 vertices but no faces"):
        validate_mesh(trimesh.Trimesh(np.array(TETRAHEDRON, float), np.zeros((0, 3), int), process=False), "cube")


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl"])
def test_empty_file_raises_mesh_error_naming_the_file(tmp_path, suffix):
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(MeshError, match=f"empty{suffix}"):
        load_mesh(path)


def test_missing_path_wrong_suffix_and_empty_folder_raise_mesh_error(tmp_path):
    with pytest.raises(MeshError, match="nowhere.ply"):
        load_mesh(tmp_path / "nowhere.ply")
    with pytest.raises(MeshError, match="nowhere"):
        load_mesh_set(tmp_path / "nowhere")
    wrong = tmp_path / "particle.glb"
    wrong.write_bytes(b"not a mesh")
    with pytest.raises(MeshError, match=r"particle\.glb.*suffix"):
        load_mesh(wrong)
    empty = tmp_path / "empty_folder"
    empty.mkdir()
    (empty / "notes.txt").write_text("no meshes here")
    with pytest.raises(MeshError, match="empty_folder"):
        load_mesh_set(empty)


def test_validate_mesh_names_the_mesh():
    with pytest.raises(MeshError, match="my particle.*empty"):
        validate_mesh(trimesh.Trimesh(), "my particle")
    with pytest.raises(MeshError, match="particle 3.*expected a triangle mesh"):
        validate_mesh(trimesh.PointCloud(np.zeros((3, 3))), "particle 3")


# --- CLI --------------------------------------------------------------------------------------------


def test_cli_writes_meshes_and_manifest(tmp_path):
    out = tmp_path / "cubes"
    command = [
        sys.executable,
        "-m",
        "drgan.meshes",
        "kind=cube",
        "count=3",
        "seed=1",
        f"out={out}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "mesh_000.ply", "mesh_001.ply", "mesh_002.ply"]
    manifest = json.loads((out / "manifest.json").read_text())
    assert (manifest["kind"], manifest["count"], manifest["seed"]) == ("cube", 3, 1)
    assert manifest["parameters"]["displacement"] == 0.1
    assert [m["faces"] for m in manifest["meshes"]] == [1200, 1200, 1200]
    expected = generate_meshes("cube", 3, seed=1)
    for mesh, path in zip(expected, sorted(out.glob("mesh_*.ply"))):
        np.testing.assert_allclose(load_mesh(path).vertices, mesh.vertices, atol=1e-6)


def test_cli_rejects_unknown_kind(tmp_path):
    command = [
        sys.executable,
        "-m",
        "drgan.meshes",
        "kind=pyramid",
        "count=1",
        f"out={tmp_path / 'x'}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert result.returncode != 0
    assert "pyramid" in result.stderr and not (tmp_path / "x").exists()


def test_missing_meshes_dir_is_named_as_the_setting(tmp_path):
    from drgan.models.build import load_particle_meshes
    from drgan.scene.config import MeshSource

    with pytest.raises(MeshError, match=r"^material\.meshes\.dir=nowhere: no such folder or mesh file \(.*nowhere\)$"):
        load_particle_meshes(MeshSource(dir="nowhere"), base_dir=tmp_path)
