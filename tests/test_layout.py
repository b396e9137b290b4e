"""Layouts Phi (m, n, 4): size distributions, placements, the Poisson agglomerates' guarantees, configs."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import compose
from hydra.utils import instantiate
from omegaconf import OmegaConf
from scipy.sparse.csgraph import connected_components

from drgan.core.errors import ConfigError
from drgan.scene.layout import particle_counts, placement_from_config, sample_layouts, size_from_config
from drgan.scene.placements import PoissonAgglomerates, Random2D, Random3D
from drgan.scene.sizes import BimodalSize, LognormalSize, NormalSize

CONF = Path(__file__).resolve().parents[1] / "src" / "drgan" / "conf" / "gan"
DRAWS = 20_000  # size samples per statistical check
LOGNORMAL = LognormalSize(median=24.0, sigma=0.2)
PLACEMENTS = [Random2D(), Random3D(max_height=24.0), PoissonAgglomerates()]


def pair_distances(layout: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All pairwise centre distances (n, n) and pairwise mean diameters (n, n) of one layout, float64."""
    layout = layout.astype(np.float64)
    gaps = layout[:, None, :3] - layout[None, :, :3]
    mean_diameter = 0.5 * (layout[:, None, 3] + layout[None, :, 3])
    return np.sqrt((gaps**2).sum(axis=2)), mean_diameter


def agglomerate_count(layout: np.ndarray, factor: float) -> int:
    """Connected groups when particles within the Bridson shell's outer radius 2 r_ij are linked."""
    distance, mean_diameter = pair_distances(layout)
    linked = distance <= 2.0 * factor * mean_diameter * (1.0 + 1e-4)
    return connected_components(linked, directed=False)[0]


def mean_kth_neighbour_distance_xy(layouts: np.ndarray, k: int) -> float:
    gaps = layouts[:, :, None, :2] - layouts[:, None, :, :2]
    distance = np.sort(np.sqrt((gaps.astype(np.float64) ** 2).sum(axis=3)), axis=2)
    return float(distance[:, :, k].mean())  # column 0 is the particle itself


# ---------------------------------------------------------------------------------------------- sizes


@pytest.mark.parametrize(
    "size",
    [
        NormalSize(mean=24.0, std=3.0),
        NormalSize(mean=3.0, std=2.0, min_size=2.0),  # heavy truncation: exact truncated moments
        LOGNORMAL,
        LognormalSize(median=10.0, sigma=0.5),
        BimodalSize(mean1=18.0, std1=2.5, mean2=32.0, std2=4.0, weight1=0.6),
    ],
)
def test_size_sample_matches_moments(size):
    sizes = size.sample(np.random.default_rng(1), DRAWS)
    mean, std = size.moments()
    assert sizes.shape == (DRAWS,)
    assert (sizes > 0).all()
    assert abs(sizes.mean() - mean) < 5 * std / math.sqrt(DRAWS)
    assert sizes.std() == pytest.approx(std, rel=0.03)


def test_normal_moments_untruncated_when_truncation_negligible():
    assert NormalSize(mean=24.0, std=3.0).moments() == pytest.approx((24.0, 3.0), rel=1e-9)


def test_normal_truncation_resamples_instead_of_clipping():
    sizes = NormalSize(mean=3.0, std=2.0, min_size=2.0).sample(np.random.default_rng(2), DRAWS)
    assert sizes.min() >= 2.0
    assert (sizes == 2.0).sum() == 0  # clipping would pile ~31 % of the draws exactly at min_size


def test_lognormal_median_and_log_spread():
    sizes = LOGNORMAL.sample(np.random.default_rng(3), DRAWS)
    assert np.median(sizes) == pytest.approx(24.0, abs=0.25)
    assert np.log(sizes).std() == pytest.approx(0.2, rel=0.03)


def test_bimodal_mixture_weight():
    size = BimodalSize(mean1=10.0, std1=1.0, mean2=40.0, std2=2.0, weight1=0.3)
    sizes = size.sample(np.random.default_rng(4), DRAWS)
    assert (sizes < 25.0).mean() == pytest.approx(0.3, abs=0.015)
    assert sizes[sizes < 25.0].mean() == pytest.approx(10.0, abs=0.1)
    assert sizes[sizes >= 25.0].mean() == pytest.approx(40.0, abs=0.1)


def test_size_sample_shape():
    assert LOGNORMAL.sample(np.random.default_rng(0), (3, 5)).shape == (3, 5)


# ---------------------------------------------------------------------------------------------- layouts


@pytest.mark.parametrize("placement", PLACEMENTS, ids=lambda p: type(p).__name__)
def test_layout_shape_dtype_and_reproducibility(placement):
    first = sample_layouts(6, 40, LOGNORMAL, placement, seed=7)
    assert first.shape == (6, 40, 4)
    assert first.dtype == np.float32
    np.testing.assert_array_equal(first, sample_layouts(6, 40, LOGNORMAL, placement, seed=7))
    assert not np.array_equal(first, sample_layouts(6, 40, LOGNORMAL, placement, seed=8))


@pytest.mark.parametrize("placement", PLACEMENTS, ids=lambda p: type(p).__name__)
def test_variable_counts_fill_the_first_rows_and_zero_the_rest(placement):
    layouts = sample_layouts(300, 12, LOGNORMAL, placement, seed=4, n_min=3)
    counts = particle_counts(layouts)
    assert counts.min() == 3 and counts.max() == 12  # both ends are drawn, nothing outside them
    assert abs(counts.mean() - 7.5) < 0.5  # uniform over 3..12
    for layout, k in zip(layouts, counts):
        assert (layout[:k, 3] > 0).all() and not layout[k:].any()
    # The present particles keep the placement's guarantees: centres in the view, none below the stage.
    present = layouts[layouts[..., 3] > 0]
    assert (np.abs(present[:, :2]) <= 128.0).all() and (present[:, 2] >= 0.5 * present[:, 3] - 1e-3).all()
    # Without n_min every row is present and the draw is the one it always was.
    full = sample_layouts(5, 12, LOGNORMAL, placement, seed=4)
    assert (particle_counts(full) == 12).all()
    np.testing.assert_array_equal(full, sample_layouts(5, 12, LOGNORMAL, placement, seed=4, n_min=None))


@pytest.mark.parametrize(
    "n_min, match",
    [(0, "n_min must be an integer >= 1"), (13, "n_min = 13 must be <= n = 12"), (2.5, "n_min must be an integer")],
)
def test_bad_n_min_is_refused(n_min, match):
    with pytest.raises(ConfigError, match=match):
        sample_layouts(2, 12, LOGNORMAL, Random2D(), n_min=n_min)


def test_material_n_particles_min_reaches_the_phi_bank():
    from drgan.models.build import sample_phi

    cfg = compose(["material=tio2_sem", "material.n_particles=10", "material.n_particles_min=4"], config_name="train")
    counts = particle_counts(sample_phi(cfg, 200, seed=0))
    assert counts.min() == 4 and counts.max() == 10
    cfg.material.n_particles_min = 11
    with pytest.raises(
        ConfigError, match=r"material.n_particles_min=11: expected null or an integer in 1..material.n_particles \(10\)"
    ):
        sample_phi(cfg, 2, seed=0)


@pytest.mark.parametrize("placement", PLACEMENTS, ids=lambda p: type(p).__name__)
@pytest.mark.parametrize("margin", [0.0, 1.0])
def test_centres_inside_view_and_above_stage(placement, margin):
    placement = dataclasses.replace(placement, margin=margin)
    view_width = 200.0
    layouts = sample_layouts(10, 40, LOGNORMAL, placement, view_width=view_width, seed=11).astype(np.float64)
    x, y, z, scale = np.moveaxis(layouts, 2, 0)
    assert (scale > 0).all()
    limit = view_width / 2 - margin * scale / 2 + 1e-4
    assert (np.abs(x) <= limit).all() and (np.abs(y) <= limit).all()
    assert (z >= scale / 2).all()  # never below the stage: exact, also in float32
    if margin == 1.0:
        # The particles reach the border: the limit is the binding one, not a much tighter one.
        assert (np.abs(x) + scale / 2).max() > 0.8 * view_width / 2


def test_random_2d_rests_on_stage_and_random_3d_stays_below_max_height():
    on_stage = sample_layouts(4, 40, LOGNORMAL, Random2D(), seed=0)
    np.testing.assert_array_equal(on_stage[..., 2], on_stage[..., 3] / 2)
    lifted = sample_layouts(4, 40, LOGNORMAL, Random3D(max_height=30.0), seed=0).astype(np.float64)
    gap = lifted[..., 2] - lifted[..., 3] / 2
    assert gap.min() >= 0.0 and gap.max() <= 30.0 + 1e-4
    assert gap.max() > 20.0  # uniform over [0, 30], not stuck on the stage


def test_random_placements_are_uniform_over_the_view():
    layouts = sample_layouts(200, 40, LOGNORMAL, Random2D(), seed=5)
    for axis in (0, 1):
        values = layouts[..., axis]
        assert abs(values.mean()) < 2.0  # uniform on [-128, 128]: std 73.9, 8000 draws, SE 0.83
        assert values.std() == pytest.approx(256 / math.sqrt(12), rel=0.03)


# ---------------------------------------------------------------------------------------------- Poisson


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize(
    "size, factor",
    [(LOGNORMAL, 0.9), (BimodalSize(mean1=12.0, std1=2.0, mean2=30.0, std2=3.0, weight1=0.5), 1.0)],
)
def test_poisson_keeps_minimum_distance_between_every_pair(seed, size, factor):
    placement = PoissonAgglomerates(min_distance_factor=factor)
    for layout in sample_layouts(4, 40, size, placement, seed=seed):
        distance, mean_diameter = pair_distances(layout)
        off_diagonal = ~np.eye(len(layout), dtype=bool)
        assert (distance[off_diagonal] >= factor * mean_diameter[off_diagonal]).all()


def test_poisson_minimum_distance_through_background_grid():
    # More than 64 particles: the neighbour search goes through the background grid.
    placement = PoissonAgglomerates(cluster_radius=96.0)
    layouts = sample_layouts(2, 300, LOGNORMAL, placement, view_width=512.0, seed=3)
    for layout in layouts:
        distance, mean_diameter = pair_distances(layout)
        off_diagonal = ~np.eye(len(layout), dtype=bool)
        assert (distance[off_diagonal] >= 0.9 * mean_diameter[off_diagonal]).all()
        assert 1 <= agglomerate_count(layout, 0.9) <= 5


@pytest.mark.parametrize("max_clusters", [1, 3, 5])
def test_poisson_agglomerate_count_within_max_clusters(max_clusters):
    placement = PoissonAgglomerates(max_clusters=max_clusters)
    layouts = sample_layouts(20, 40, LOGNORMAL, placement, view_width=1024.0, seed=max_clusters)
    counts = [agglomerate_count(layout, 0.9) for layout in layouts]
    assert min(counts) >= 1 and max(counts) <= max_clusters
    if max_clusters > 1:
        assert max(counts) > 1  # the number of clusters is drawn, not always one


def test_poisson_particles_are_clustered_unlike_uniform_placement():
    agglomerates = sample_layouts(20, 40, LOGNORMAL, PoissonAgglomerates(), view_width=1024.0, seed=1)
    uniform = sample_layouts(20, 40, LOGNORMAL, Random2D(), view_width=1024.0, seed=1)
    assert mean_kth_neighbour_distance_xy(agglomerates, 5) < 0.5 * mean_kth_neighbour_distance_xy(uniform, 5)


def test_poisson_piles_particles_up_to_max_height():
    piled = sample_layouts(20, 40, LOGNORMAL, PoissonAgglomerates(max_height=48.0), seed=2).astype(np.float64)
    gap = piled[..., 2] - piled[..., 3] / 2
    assert gap.min() >= 0.0 and gap.max() <= 48.0 + 1e-4
    assert (gap == 0.0).mean() > 0.3  # the bottom layer rests on the stage
    assert (gap > 5.0).any()  # and some particles sit on others
    flat = sample_layouts(4, 40, LOGNORMAL, PoissonAgglomerates(max_height=0.0), seed=2)
    np.testing.assert_array_equal(flat[..., 2], flat[..., 3] / 2)


def test_poisson_paper_sized_layouts_place_every_particle():
    """The paper's size (124 constellations of 40 particles): every particle placed, inside the view's depth range.
    (Its speed, ~0.3 s of CPU, is a benchmark's business, not a test's.)"""
    phi = np.asarray(sample_layouts(124, 40, LOGNORMAL, PoissonAgglomerates(), seed=0))
    assert phi.shape == (124, 40, 4) and np.all(np.isfinite(phi)) and np.all(phi[..., 3] > 0)


def test_poisson_impossible_packing_raises():
    crowded = PoissonAgglomerates(max_height=0.0)
    with pytest.raises(ConfigError, match=r"too many particles.*\(constellation 0: 51 draws of sizes\)"):
        sample_layouts(1, 100, NormalSize(mean=24.0, std=0.0), crowded, view_width=64.0)


def test_a_draw_of_sizes_too_large_for_the_view_is_drawn_again():
    """EMPS apsusc's profiled material (104 px spheres, lognormal sigma 0.38, 3-6 per 256 px view) could not place
    3 % of its draws, so training stopped at its start: such a constellation now draws its sizes again. Draws that
    fit the first time are the ones they always were."""
    size, placement = LognormalSize(median=114.0, sigma=0.38), PoissonAgglomerates(max_height=228.0)
    rng_draws = []
    for seed in range(200):  # which single draws fail without the redraw
        rng = np.random.default_rng(seed)
        sizes = size.sample(rng, (1, 6))
        k = int(rng.integers(3, 7, size=1)[0])
        try:
            placement.sample(rng, sizes[0, :k], 256.0)
        except ConfigError:
            rng_draws.append(seed)
    assert rng_draws  # the distribution does hold layouts that cannot be placed
    for seed in rng_draws[:3]:
        phi = sample_layouts(1, 6, size, placement, view_width=256.0, seed=seed, n_min=3)
        assert 3 <= particle_counts(phi)[0] <= 6 and np.isfinite(phi).all()
    fits = next(s for s in range(200) if s not in rng_draws)
    rng = np.random.default_rng(fits)
    sizes = size.sample(rng, (1, 6))
    k = int(rng.integers(3, 7, size=1)[0])
    np.testing.assert_array_equal(
        sample_layouts(1, 6, size, placement, view_width=256.0, seed=fits, n_min=3)[0, :k, 3],
        sizes[0, :k].astype(np.float32),
    )


# ---------------------------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize(
    "build, field",
    [
        (lambda: NormalSize(mean=24.0, std=-1.0), "std"),
        (lambda: NormalSize(mean=0.5, std=1.0), "mean"),
        (lambda: NormalSize(mean=24.0, std=3.0, min_size=0.0), "min_size"),
        (lambda: NormalSize(mean=float("nan"), std=3.0), "mean"),
        (lambda: NormalSize(mean="24", std=3.0), "mean"),
        (lambda: LognormalSize(median=24.0, sigma=0.0), "sigma"),
        (lambda: LognormalSize(median=24.0, sigma=-0.2), "sigma"),
        (lambda: LognormalSize(median=-1.0, sigma=0.2), "median"),
        (lambda: BimodalSize(18.0, 2.5, 32.0, 4.0, weight1=1.5), "weight1"),
        (lambda: BimodalSize(18.0, 2.5, 32.0, 4.0, weight1=-0.1), "weight1"),
        (lambda: BimodalSize(18.0, 2.5, 32.0, -4.0, weight1=0.5), "std2"),
        (lambda: Random2D(margin=-1.0), "margin"),
        (lambda: Random3D(max_height=-1.0), "max_height"),
        (lambda: PoissonAgglomerates(max_clusters=0), "max_clusters"),
        (lambda: PoissonAgglomerates(max_clusters=2.5), "max_clusters"),
        (lambda: PoissonAgglomerates(min_distance_factor=0.0), "min_distance_factor"),
        (lambda: PoissonAgglomerates(cluster_radius=-5.0), "cluster_radius"),
        (lambda: PoissonAgglomerates(attempts=0), "attempts"),
        (lambda: sample_layouts(0, 40, LOGNORMAL, Random2D()), "m"),
        (lambda: sample_layouts(4, 0, LOGNORMAL, Random2D()), "n"),
        (lambda: sample_layouts(4, 40, LOGNORMAL, Random2D(), view_width=0.0), "view_width"),
        (lambda: sample_layouts(4, 40, Random2D(), LOGNORMAL), "size"),
        (lambda: sample_layouts(1, 4, LOGNORMAL, Random2D(margin=1.0), view_width=10.0), "margin"),
    ],
)
def test_bad_inputs_raise_config_error_naming_the_field(build, field):
    with pytest.raises(ConfigError, match=rf"\b{field}\b"):
        build()


# ---------------------------------------------------------------------------------------------- configs


@pytest.mark.parametrize(
    "group, name, expected",
    [
        ("size", "normal", NormalSize),
        ("size", "lognormal", LognormalSize),
        ("size", "bimodal", BimodalSize),
        ("placement", "random_2d", Random2D),
        ("placement", "random_3d", Random3D),
        ("placement", "poisson", PoissonAgglomerates),
    ],
)
def test_config_group_files_build_their_dataclass(group, name, expected):
    cfg = compose([f"{group}={name}"])[group]
    build = size_from_config if group == "size" else placement_from_config
    built = build(cfg)
    assert type(built) is expected
    # Every field is spelled out in the file, so the defaults are visible where they are changed.
    assert set(cfg) == {field.name for field in dataclasses.fields(expected)} | {"_target_"}
    # The class the file names is the one Hydra would instantiate, too.
    assert cfg._target_ == f"{expected.__module__}.{expected.__qualname__}"
    assert type(instantiate(cfg)) is expected
    assert build(OmegaConf.to_container(cfg, resolve=True)) == built


def test_config_files_sample_paper_like_layouts():
    cfg = compose(["material=tio2_sem", "size=lognormal", "placement=poisson"])
    size, placement = size_from_config(cfg.size), placement_from_config(cfg.placement)
    layouts = sample_layouts(4, 40, size, placement)
    assert layouts.shape == (4, 40, 4)
    assert 0.8 * cfg.material.particle_size_px < np.median(layouts[..., 3]) < 1.25 * cfg.material.particle_size_px


def test_config_target_must_name_a_known_class():
    with pytest.raises(ConfigError, match=r"size._target_ must be one of.*LognormalSize.*got 'os.system'"):
        size_from_config({"_target_": "os.system", "median": 24.0})
    with pytest.raises(
        ConfigError, match=r"placement._target_ must be one of.*PoissonAgglomerates.*Random2D.*got None"
    ):
        placement_from_config({"kind": "grid"})


def test_config_unknown_field_lists_valid_fields():
    with pytest.raises(ConfigError, match=r"stdev.*expected some of.*mean.*std.*min_size"):
        size_from_config({"_target_": "drgan.scene.sizes.NormalSize", "mean": 24.0, "stdev": 3.0})
    with pytest.raises(ConfigError, match=r"radius.*expected some of.*cluster_radius"):
        placement_from_config({"_target_": "drgan.scene.placements.PoissonAgglomerates", "radius": 10.0})


def test_config_missing_field_raises_config_error():
    with pytest.raises(ConfigError, match="sigma"):
        size_from_config({"_target_": "drgan.scene.sizes.LognormalSize", "median": 24.0})


def test_config_values_are_validated():
    with pytest.raises(ConfigError, match="sigma"):
        size_from_config({"_target_": "drgan.scene.sizes.LognormalSize", "median": 24.0, "sigma": -1.0})


def test_the_former_import_paths_of_sizes_and_placements_build_the_same_classes():
    """Checkpoints saved before the classes left drgan.scene.layout name them there; anything else stays refused."""
    size = size_from_config({"_target_": "drgan.scene.layout.LognormalSize", "median": 24.0, "sigma": 0.2})
    assert size == LognormalSize(median=24.0, sigma=0.2)
    placement = placement_from_config({"_target_": "drgan.scene.layout.PoissonAgglomerates", "max_clusters": 2})
    assert placement == PoissonAgglomerates(max_clusters=2)
    with pytest.raises(ConfigError, match=r"size\._target_ must be one of"):
        size_from_config({"_target_": "drgan.scene.layout.Random2D"})
    with pytest.raises(ConfigError, match=r"placement\._target_ must be one of"):
        placement_from_config({"_target_": "drgan.scene.layout.sample_layouts"})
