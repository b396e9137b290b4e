"""Placements of a layout (drgan.scene.layout): particle centres (x, y, z) in px, given the diameters.

Each is a frozen dataclass checked at construction, built from a ``conf/gan/placement/*.yaml`` config whose
``_target_`` names it (`drgan.scene.layout.placement_from_config`); ``sample(rng, sizes, view_width)`` returns the
(n, 3) centres. Units and frame as in drgan.scene.layout. numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drgan.core.errors import ConfigError, check_int_at_least, check_non_negative, check_positive

__all__ = ["Random2D", "Random3D", "PoissonAgglomerates", "OfficialPlacement", "Placement"]


def _half_extents(owner: str, sizes: np.ndarray, view_width: float, margin: float) -> np.ndarray:
    """Largest |x|, |y| of each particle centre: W/2 minus ``margin`` particle radii."""
    half = 0.5 * view_width - margin * 0.5 * sizes
    if (half < 0.0).any():
        raise ConfigError(
            f"{owner}.margin = {margin} radii does not fit a particle of diameter {sizes.max():.3g} px "
            f"in a view of width {view_width} px; lower margin or the particle size"
        )
    return half


def _check_sizes(owner: str, sizes: np.ndarray, view_width: float) -> np.ndarray:
    sizes = np.asarray(sizes, dtype=np.float64)
    if sizes.ndim != 1 or sizes.size == 0:
        raise ConfigError(f"{owner}.sample: sizes must be a non-empty 1-D array, got shape {sizes.shape}")
    if not np.isfinite(sizes).all() or (sizes <= 0.0).any():
        raise ConfigError(f"{owner}.sample: sizes must be finite and > 0 px, got min {sizes.min()!r}")
    check_positive(owner, "view_width", view_width)
    return sizes


@dataclass(frozen=True)
class Random2D:
    """Every particle rests on the stage (z = scale / 2) at a uniform x, y; particles may overlap.

    margin: distance kept from the view border in particle radii (0: centre inside the view;
    1: particle fully inside).
    """

    margin: float = 0.0

    def __post_init__(self) -> None:
        check_non_negative("Random2D", "margin", self.margin)

    def sample(self, rng: np.random.Generator, sizes: np.ndarray, view_width: float) -> np.ndarray:
        """Centres (n, 3) in px for diameters ``sizes`` (n,) in px."""
        sizes = _check_sizes("Random2D", sizes, view_width)
        half = _half_extents("Random2D", sizes, view_width, self.margin)
        xy = rng.uniform(-1.0, 1.0, (sizes.size, 2)) * half[:, None]
        return np.column_stack([xy, 0.5 * sizes])


@dataclass(frozen=True)
class Random3D:
    """Uniform x, y; the gap between particle bottom and stage uniform in [0, max_height] px.

    So z is uniform in [scale / 2, scale / 2 + max_height]. Particles may overlap.
    margin: distance kept from the view border in particle radii (see Random2D).
    """

    max_height: float = 24.0
    margin: float = 0.0

    def __post_init__(self) -> None:
        check_non_negative("Random3D", "max_height", self.max_height)
        check_non_negative("Random3D", "margin", self.margin)

    def sample(self, rng: np.random.Generator, sizes: np.ndarray, view_width: float) -> np.ndarray:
        """Centres (n, 3) in px for diameters ``sizes`` (n,) in px."""
        sizes = _check_sizes("Random3D", sizes, view_width)
        half = _half_extents("Random3D", sizes, view_width, self.margin)
        xy = rng.uniform(-1.0, 1.0, (sizes.size, 2)) * half[:, None]
        z = 0.5 * sizes + rng.uniform(0.0, self.max_height, sizes.size)
        return np.column_stack([xy, z])


# Distances are accepted only if they beat the minimum by this relative margin, so the guarantee still
# holds after Phi is rounded to float32 (relative rounding ~6e-8 per coordinate).
_DISTANCE_SAFETY = 1.0 + 1e-5
# Tries to put a new cluster centre where it keeps the minimum distance to the earlier centres.
_CENTRE_TRIES = 100
# Each time every cluster is full, the cluster radius grows by this factor.
_CLUSTER_GROWTH = 1.5
# Below this many placed particles, checking all of them is cheaper than reading the background grid.
_GRID_FROM = 64


class _BackgroundGrid:
    """Bridson's background grid over the box x, y in [-W/2, W/2], z in [0, top], for fast neighbour queries.

    Bridson (2007) uses cells of side r / sqrt(d) so that each cell holds at most one sample. Here radii vary
    with the particle pair, so the cells have side >= the largest pair distance instead and each holds a few
    point indices; a query reads the block of cells around a point.
    """

    def __init__(self, view_width: float, top: float, cell: float, capacity: int = 4) -> None:
        self.origin = (-0.5 * view_width, -0.5 * view_width, 0.0)
        self.cell = cell
        self.sizes = (int(view_width // cell) + 1, int(view_width // cell) + 1, int(top // cell) + 1)
        self.points = np.full((*self.sizes, capacity), -1, dtype=np.int64)
        self.counts = np.zeros(self.sizes, dtype=np.int64)

    def cell_of(self, position: np.ndarray) -> tuple[int, int, int]:
        # Plain Python arithmetic: this runs once per query on 3 numbers, where numpy calls cost more.
        x, y, z = position.tolist()
        nx, ny, nz = self.sizes
        return (
            min(max(int((x - self.origin[0]) // self.cell), 0), nx - 1),
            min(max(int((y - self.origin[1]) // self.cell), 0), ny - 1),
            min(max(int((z - self.origin[2]) // self.cell), 0), nz - 1),
        )

    def insert(self, point_index: int, position: np.ndarray) -> None:
        ix, iy, iz = self.cell_of(position)
        count = self.counts[ix, iy, iz]
        if count == self.points.shape[3]:
            grown = np.full((*self.sizes, 2 * count), -1, dtype=np.int64)
            grown[..., :count] = self.points
            self.points = grown
        self.points[ix, iy, iz, count] = point_index
        self.counts[ix, iy, iz] = count + 1

    def near(self, position: np.ndarray, distance: float) -> np.ndarray:
        """Indices of all stored points within ``distance`` px of ``position`` (and possibly a few more)."""
        ix, iy, iz = self.cell_of(position)
        reach = int(distance // self.cell) + 1
        block = self.points[
            max(ix - reach, 0) : ix + reach + 1,
            max(iy - reach, 0) : iy + reach + 1,
            max(iz - reach, 0) : iz + reach + 1,
        ]
        block = block.ravel()
        return block[block >= 0]


class _ShellDraws:
    """Random numbers for Bridson attempts, drawn in batches (one numpy call per batch, not per attempt).

    Each attempt gets k offsets uniform in volume in the unit shell 1 <= |offset| <= 2 (scaled by r later)
    and two uniforms in [0, 1) that pick the cluster and the active particle.
    """

    def __init__(self, rng: np.random.Generator, k: int, batch: int) -> None:
        self.rng, self.k, self.batch = rng, k, batch
        self.used = batch

    def next(self) -> tuple[np.ndarray, float, float]:
        if self.used == self.batch:
            directions = self.rng.standard_normal((self.batch, self.k, 3))
            directions /= np.linalg.norm(directions, axis=2, keepdims=True)
            # Radius with density ~ rho^2 on [1, 2]: uniform in volume.
            self.offsets = directions * np.cbrt(1.0 + 7.0 * self.rng.random((self.batch, self.k, 1)))
            self.picks = self.rng.random((self.batch, 2)).tolist()
            self.used = 0
        i = self.used
        self.used += 1
        return self.offsets[i], self.picks[i][0], self.picks[i][1]


@dataclass(frozen=True)
class PoissonAgglomerates:
    """Agglomerates of piled particles grown by Bridson (2007) Poisson-disk sampling in 3-D.

    Minimum distance: the centres of particles i and j (diameters s_i, s_j, px) are never closer than
        min_distance_factor * (s_i + s_j) / 2,
    over every pair in the layout (so 1.0 means touching spheres, < 1 lets neighbours interpenetrate a bit,
    as sintered particles do).

    Sampling: a number of clusters uniform in [1, max_clusters]; each cluster starts with one particle resting
    on the stage at a uniform x, y (the cluster centre). Then each further particle picks a cluster at random,
    an active particle p of it at random, and tries ``attempts`` (Bridson's k) candidates uniform in the 3-D
    shell [r, 2r] around p, r = min_distance_factor * (s_p + s_new) / 2; a candidate below the stage is lifted
    to z = s_new / 2 (so agglomerates are piles on the stage). The first candidate that keeps the minimum
    distance to every particle, stays within 2r of p, within ``cluster_radius`` of its cluster centre, inside
    the view and at most ``max_height`` above the stage is taken; if none is, p is retired (Bridson's active
    list). When every cluster is full, the cluster radius grows by 1.5x and all particles become active
    again, until it spans the whole view; a layout that still cannot host n particles raises ConfigError.
    Every particle is within 2r of the particle it grew from, so each cluster is connected.

    max_clusters: most agglomerates per layout (>= 1).
    min_distance_factor: see above (> 0).
    cluster_radius: px, initial 3-D radius of an agglomerate around its centre (> 0).
    max_height: px, largest gap between particle bottom and stage, z <= scale / 2 + max_height (>= 0).
    attempts: Bridson's k, candidates tried around an active particle before it is retired (>= 1).
    margin: distance kept from the view border in particle radii (see Random2D).
    """

    max_clusters: int = 5
    min_distance_factor: float = 0.9
    cluster_radius: float = 48.0
    max_height: float = 48.0
    attempts: int = 30
    margin: float = 0.0

    def __post_init__(self) -> None:
        check_int_at_least("PoissonAgglomerates", "max_clusters", self.max_clusters, 1)
        check_positive("PoissonAgglomerates", "min_distance_factor", self.min_distance_factor)
        check_positive("PoissonAgglomerates", "cluster_radius", self.cluster_radius)
        check_non_negative("PoissonAgglomerates", "max_height", self.max_height)
        check_int_at_least("PoissonAgglomerates", "attempts", self.attempts, 1)
        check_non_negative("PoissonAgglomerates", "margin", self.margin)

    def sample(self, rng: np.random.Generator, sizes: np.ndarray, view_width: float) -> np.ndarray:
        """Centres (n, 3) in px for diameters ``sizes`` (n,) in px; raises ConfigError if they cannot fit.

        Long because it is one loop over one random stream: Bridson's active lists, the clusters' growth and the
        shell draws share its state, and every constellation a checkpoint or a dataset recorded depends on the
        order of its draws."""
        sizes = _check_sizes("PoissonAgglomerates", sizes, view_width)
        half = _half_extents("PoissonAgglomerates", sizes, view_width, self.margin)
        n = sizes.size
        factor = float(self.min_distance_factor)
        k = int(self.attempts)
        # Minimum centre distance of pair (i, j) is exclusion[i] + exclusion[j] (with the float32 safety margin).
        exclusion = factor * 0.5 * _DISTANCE_SAFETY * sizes
        largest_exclusion = float(exclusion.max())
        max_height = float(self.max_height)
        # Bound on |x|, |y|, z of each centre (z >= scale / 2 holds by construction).
        upper = np.column_stack([half, half, 0.5 * sizes + max_height])
        top = float(upper[:, 2].max())
        # Cells at least as wide as the largest pair distance; coarser when that is tiny (<= ~64^3 cells).
        cell = max(2.0 * largest_exclusion, max(view_width, top) / 64.0)
        grid = _BackgroundGrid(view_width, top, cell)
        positions = np.zeros((n, 3))

        def keeps_distance(candidates: np.ndarray, i: int, others: np.ndarray | slice) -> np.ndarray:
            gaps = candidates[:, None, :] - positions[others]
            squared = np.einsum("ijk,ijk->ij", gaps, gaps)
            return (squared >= (exclusion[i] + exclusion[others]) ** 2).all(axis=1)

        # Cluster centres: the first particles, resting on the stage at uniform x, y.
        n_clusters = min(int(rng.integers(1, int(self.max_clusters) + 1)), n)
        centres: list[int] = []
        for i in range(n_clusters):
            for _ in range(_CENTRE_TRIES):
                candidate = np.array([*rng.uniform(-half[i], half[i], 2), 0.5 * sizes[i]])
                others = slice(0, i) if i < _GRID_FROM else grid.near(candidate, exclusion[i] + largest_exclusion)
                if keeps_distance(candidate[None], i, others)[0]:
                    positions[i] = candidate
                    grid.insert(i, candidate)
                    centres.append(i)
                    break
            else:
                break  # no room for another centre: the remaining particles grow the existing clusters
        members = [[centre] for centre in centres]
        active = [[centre] for centre in centres]
        radius = float(self.cluster_radius)
        full_radius = math.sqrt(2.0) * view_width + top  # from any centre, reaches the whole box

        shells = _ShellDraws(rng, k, batch=max(n, 16))
        placed = len(centres)
        while placed < n:
            open_clusters = [c for c in range(len(centres)) if active[c]]
            if not open_clusters:
                if radius >= full_radius:
                    raise ConfigError(
                        f"PoissonAgglomerates could place only {placed} of n = {n} particles "
                        f"(mean diameter {sizes.mean():.3g} px, min_distance_factor {factor}) in a view of "
                        f"width {view_width} px and max_height {max_height} px: too many particles for "
                        f"the volume; lower n, the sizes or min_distance_factor, or raise max_height"
                    )
                radius = min(radius * _CLUSTER_GROWTH, full_radius)
                active = [list(cluster) for cluster in members]
                continue
            unit_offsets, pick_cluster, pick_parent = shells.next()
            cluster = open_clusters[int(pick_cluster * len(open_clusters))]
            slot = int(pick_parent * len(active[cluster]))
            parent = active[cluster][slot]
            size = float(sizes[placed])
            pair_distance = factor * 0.5 * (float(sizes[parent]) + size)

            # k candidates uniform in volume in the shell [r, 2r] around the parent.
            parent_position = positions[parent]
            candidates = parent_position + pair_distance * unit_offsets
            np.maximum(candidates[:, 2], 0.5 * size, out=candidates[:, 2])  # lifted onto the stage
            centre = centres[cluster]
            if placed < _GRID_FROM:
                # Few particles: checking all of them is cheaper than reading the grid.
                others: np.ndarray | slice = slice(0, placed)
                parent_column, centre_column = parent, centre
            else:
                reach = 2.0 * pair_distance + exclusion[placed] + largest_exclusion
                others = np.append(grid.near(parent_position, reach), (parent, centre))
                parent_column, centre_column = -2, -1
            gaps = candidates[:, None, :] - positions[others]
            squared = np.einsum("ijk,ijk->ij", gaps, gaps)
            ok = (
                (squared >= (exclusion[placed] + exclusion[others]) ** 2).all(axis=1)
                & (squared[:, parent_column] <= 4.0 * pair_distance**2)
                & (squared[:, centre_column] <= radius**2)
                & (np.abs(candidates) <= upper[placed]).all(axis=1)
            )
            first = int(ok.argmax())
            if ok[first]:
                positions[placed] = candidates[first]
                grid.insert(placed, candidates[first])
                members[cluster].append(placed)
                active[cluster].append(placed)
                placed += 1
            else:
                active[cluster][slot] = active[cluster][-1]  # retire the parent (swap-remove)
                active[cluster].pop()
        return positions


# The official code's neighbour candidates: a 16 x 16 grid over the sphere (or circle) of radius r_parent + r_new.
_OFFICIAL_GRID = 16
# Parents tried by the official Poisson placement before it gives up (the official code loops for ever).
_OFFICIAL_PARENT_TRIES = 10_000
_OFFICIAL_ALGORITHMS = ("random", "poisson")


@dataclass(frozen=True)
class OfficialPlacement:
    """The official DiffRenderGAN code's placement (`drgan.import_official`): positions in its layout units.

    Unlike drgan's placements, sizes and positions are not in px: a row is (x, y, z, r) with x, y, z uniform in
    [-limit, limit] (z = 0 unless ``position3d``) and r the size factor the size distribution draws; the scene
    (`drgan.scene.official.OfficialScene`) turns units into geometry (x mesh_unit, r x mesh_scale). The n particles
    are split into ``max_agglomerates`` runs of random lengths (n must be divisible by it). ``algorithm``:
    "random" places each uniformly (overlaps allowed); "poisson" seeds each agglomerate at a uniform point clear of
    the earlier ones and grows it: around a random placed particle, the next size takes the first free point of a
    16 x 16 grid on the sphere (circle in 2-D) at distance r_parent + r_new, visited in random order; two particles
    are clear when their centres are >= r_i + r_j apart. Rows come in the order placed: the FCN reads that order.

    limit: half side of the box of seeds, layout units (> 0); the official mesh_base_sample_limit / mesh_unit.
    """

    algorithm: str = "poisson"
    limit: float = 1.0
    position3d: bool = False
    max_agglomerates: int = 1

    def __post_init__(self) -> None:
        if self.algorithm not in _OFFICIAL_ALGORITHMS:
            raise ConfigError(
                f"OfficialPlacement.algorithm must be one of {_OFFICIAL_ALGORITHMS}, got {self.algorithm!r}"
            )
        check_positive("OfficialPlacement", "limit", self.limit)
        if not isinstance(self.position3d, bool):
            raise ConfigError(f"OfficialPlacement.position3d must be true or false, got {self.position3d!r}")
        check_int_at_least("OfficialPlacement", "max_agglomerates", self.max_agglomerates, 1)

    def sample(self, rng: np.random.Generator, sizes: np.ndarray, view_width: float) -> np.ndarray:
        """Centres (n, 3) in layout units for sizes (n,); ``view_width`` is not used (the box is ``limit``)."""
        sizes = _check_sizes("OfficialPlacement", sizes, view_width)
        n, k = sizes.size, int(self.max_agglomerates)
        if n % k:
            raise ConfigError(f"OfficialPlacement: n = {n} particles cannot be split into max_agglomerates = {k}")
        lengths = rng.integers(1, n // k + 1, size=k)
        lengths[-1] = n - lengths[:-1].sum()
        placed = np.zeros((0, 4))
        start = 0
        for length in lengths:
            radii = sizes[start : start + length]
            start += length
            if self.algorithm == "random":
                rows = np.column_stack([self._uniform(rng, len(radii)), radii])
            else:
                rows = self._grow(rng, radii, placed)
            placed = np.concatenate([placed, rows])
        return placed[:, :3]

    def _uniform(self, rng: np.random.Generator, count: int) -> np.ndarray:
        xyz = rng.uniform(-self.limit, self.limit, (count, 3))
        if not self.position3d:
            xyz[:, 2] = 0.0
        return xyz

    def _grow(self, rng: np.random.Generator, radii: np.ndarray, earlier: np.ndarray) -> np.ndarray:
        """Rows (x, y, z, r) of one agglomerate, in the order of ``radii``. The official code takes the sizes from
        the end of its list and so writes each agglomerate's rows in reverse; the sizes being independent draws,
        taking them from the front gives the same distribution of Phi, rows aligned with ``sizes``."""
        for _ in range(_OFFICIAL_PARENT_TRIES):
            seed = self._uniform(rng, 1)[0]
            if not _overlaps(seed[None], radii[0], earlier).any():
                break
        else:
            raise ConfigError(f"OfficialPlacement: no room for another agglomerate within limit {self.limit}")
        rows = [np.array([*seed, radii[0]])]
        for _ in range(_OFFICIAL_PARENT_TRIES):
            parent = rows[int(rng.integers(len(rows)))]
            while len(rows) < len(radii):
                radius = radii[len(rows)]
                candidates = _neighbour_grid(parent, radius, self.position3d)
                free = ~_overlaps(candidates, radius, np.concatenate([np.array(rows), earlier]))
                visit = rng.permutation(len(candidates))
                first = visit[free[visit]]
                if not len(first):
                    break
                rows.append(np.array([*candidates[first[0]], radius]))
            if len(rows) == len(radii):
                return np.array(rows)
        raise ConfigError(f"OfficialPlacement: placed only {len(rows)} of the {len(radii)} particles of an agglomerate")


def _neighbour_grid(parent: np.ndarray, radius: float, position3d: bool) -> np.ndarray:
    """The official candidates around ``parent`` (x, y, z, r): (256, 3) points at distance r + ``radius``."""
    distance = parent[3] + radius
    theta, phi = np.meshgrid(np.linspace(0, 2 * np.pi, _OFFICIAL_GRID), np.linspace(0, np.pi, _OFFICIAL_GRID))
    if position3d:
        offsets = (np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi))
        return np.column_stack([distance * o.ravel() + c for o, c in zip(offsets, parent[:3])])
    x, y = distance * np.cos(theta) + parent[0], distance * np.sin(theta) + parent[1]
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(theta.size)])


def _overlaps(points: np.ndarray, radius: float, rows: np.ndarray) -> np.ndarray:
    """(k,) whether each point, a particle of ``radius``, overlaps any of ``rows`` (x, y, z, r): centres < r + r'."""
    if not len(rows):
        return np.zeros(len(points), dtype=bool)
    gaps = np.linalg.norm(points[:, None, :] - rows[None, :, :3], axis=-1)
    return (gaps < radius + rows[None, :, 3]).any(axis=1)


Placement = Random2D | Random3D | PoissonAgglomerates | OfficialPlacement
