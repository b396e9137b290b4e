"""Where test_scene's rectangle test fails on cuda_ad_rgb (experiments/gpu/README.md, "Open"): the same 4,000 rays
against `rectangle_mesh` (two triangles) and Mitsuba's `rectangle`, compared once with Dr.Jit's reductions (as the
test did) and once in numpy, so that a disagreement of the surfaces and one of the reductions read apart. Found on
the fifth lent GPU: the lazily fused comparison traced both scenes in one OptiX kernel, which Dr.Jit refuses
("more than one OptiX shader binding table ... Disabling this ray tracing operation"); evaluated apart, they agree.

    DRGAN_VARIANT=cuda_ad_rgb python experiments/gpu/probe_rectangle.py      # on a lent GPU (check.sh step "probe")
    python experiments/gpu/probe_rectangle.py                                 # the CPU's llvm_ad_rgb, for comparison
"""

from __future__ import annotations

import os

import numpy as np

from drgan import backend

backend.use_variant(os.environ.get("DRGAN_VARIANT", "auto"))
from drgan.backend import dr, mi  # noqa: E402  (after the variant is set)
from drgan.scene.scene import rectangle_mesh  # noqa: E402


def main() -> None:
    print("variant", mi.variant())
    to_world = mi.ScalarTransform4f().translate([1, -2, 5]).rotate([1, 0.3, 0], 160).scale([3, 2, 1])
    tri = mi.load_dict({"type": "scene", "shape": rectangle_mesh("lamp", to_world)})
    rect = mi.load_dict({"type": "scene", "shape": {"type": "rectangle", "to_world": to_world}})
    xy = np.random.default_rng(0).uniform(-5, 5, (2, 4000)).astype(np.float32)
    rays = mi.Ray3f(mi.Point3f(mi.Float(xy[0]), mi.Float(xy[1]), 0.0), mi.Vector3f(0.05, -0.1, 1.0))
    a, b = tri.ray_intersect(rays), rect.ray_intersect(rays)
    va, vb = np.array(a.is_valid()), np.array(b.is_valid())
    both = va & vb
    print(f"hits: triangles {va.sum()}, rectangle {vb.sum()}, disagree {(va != vb).sum()}")
    na, nb = np.array(a.n), np.array(b.n)  # (3, N) on every Dr.Jit version drgan supports
    if na.shape[0] != 3:
        na, nb = na.T, nb.T
    dot = (na * nb).sum(axis=0)
    print(f"numpy: min dot over hits {dot[both].min():.7f}, hits with dot < 0.999: {(dot[both] < 0.999).sum()}")
    for name, n in (("triangles", na), ("rectangle", nb)):
        length = np.linalg.norm(n, axis=0)
        print(
            f"  {name}: |n| over hits in [{length[both].min():.6f}, {length[both].max():.6f}], "
            f"non-finite over all rays {(~np.isfinite(n)).any(axis=0).sum()}, over misses "
            f"{(~np.isfinite(n[:, ~both])).any(axis=0).sum()}"
        )
    bad = np.flatnonzero(both & (dot < 0.999))[:5]
    for i in bad:
        print(f"  ray {i}: n_tri {na[:, i]}, n_rect {nb[:, i]}, t {np.array(a.t)[i]:.6f} / {np.array(b.t)[i]:.6f}")
    # the test's own expressions, through Dr.Jit's reductions
    hit = a.is_valid()
    selected = dr.select(hit, dr.dot(a.n, b.n), 1.0)
    print(
        "drjit: dr.all(valid == valid)",
        dr.all(a.is_valid() == b.is_valid()),
        "| dr.min(select(hit, dot, 1))",
        dr.min(selected),
        "| numpy min of the same array",
        np.array(selected).min(),
        "| dr.max(select(hit, |dt|/t, 0))",
        dr.max(dr.select(hit, dr.abs(a.t - b.t) / b.t, 0.0)),
    )
    # the same with each scene's intersection evaluated in a kernel of its own (what the test now does)
    a = tri.ray_intersect(rays)
    dr.eval(a)
    b = rect.ray_intersect(rays)
    dr.eval(b)
    hit = a.is_valid()
    print(
        "drjit, evaluated apart: dr.all(valid == valid)",
        dr.all(a.is_valid() == b.is_valid()),
        "| dr.min(select(hit, dot, 1))",
        dr.min(dr.select(hit, dr.dot(a.n, b.n), 1.0)),
    )
    ones = mi.Float(np.ones(4000, np.float32))
    print(
        "drjit: dr.min of 4,000 ones",
        dr.min(ones),
        "| dr.min of dr.select(mask, ones, 1.0)",
        dr.min(dr.select(hit, ones, 1.0)),
        "| dr.all(a mask == itself)",
        dr.all(hit == hit),
    )


if __name__ == "__main__":
    main()
