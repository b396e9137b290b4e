"""Shared fixtures: tiny scenes (16-32 px, few spp) so the default run stays fast on 2 CPU cores."""

from __future__ import annotations

import os

import numpy as np
import pytest

# The Mitsuba variant of the render and gradient tests: llvm_ad_rgb (CPU) unless DRGAN_TEST_VARIANT names another,
# e.g. `DRGAN_TEST_VARIANT=cuda_ad_rgb pytest tests/test_scene.py` on a GPU machine (one variant per process).
TEST_VARIANT = os.environ.get("DRGAN_TEST_VARIANT", "llvm_ad_rgb")

PAPER_PARTICLE = {
    name: {"min": 0.01, "max": 5.0} for name in ("roughness", "base_color", "sheen", "sheen_tint", "spec_tint")
}
PAPER_STAGE = {"base_color": {"min": 0.01, "max": 0.4}}
PAPER_SIGMA = {"min": 0.001, "max": 0.1}

# Four particles well inside a 64 px view, two of them overlapping.
TINY_PHI = np.array(
    [[-15, -10, 8, 16], [12, 8, 9, 18], [0, 14, 6, 12], [-8, 12, 7, 14]],
    dtype=np.float32,
)


def make_scene(
    resolution=16, spp=4, n=4, integrator="prb_basic", particle=None, stage=PAPER_STAGE, sigma=PAPER_SIGMA, **spec_kw
):
    from drgan.scene import particle_meshes
    from drgan.scene.config import SecondaryImaging
    from drgan.scene.scene import ParticleScene, RenderSettings, SceneSpec

    params = SecondaryImaging(
        particle_bsdf=PAPER_PARTICLE if particle is None else particle, stage_bsdf=stage
    ).material_parameters(sigma)
    spec = SceneSpec(
        params,
        RenderSettings(
            resolution=resolution, spp=spp, integrator=integrator, filter_stddev=spec_kw.pop("filter_stddev", 0.5)
        ),
        view_width=spec_kw.pop("view_width", 64.0),
        stage=stage is not None,
        **spec_kw,
    )
    return ParticleScene([particle_meshes.sphere(2)], n, spec, variant=TEST_VARIANT)


@pytest.fixture
def one_torch_thread():
    """Training-like tests: two cores are shared with Dr.Jit's own thread pool, and torch's second thread
    only adds contention there (a 24 px discriminator step took 0.75 s with 2 threads, 0.05 s with 1)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def one_render_thread():
    """Bitwise-repeatable adjoint passes: Dr.Jit sums a gradient from its threads in no fixed order, so two
    identical renders' gradients differ in the last float32 bits (up to ~1e-4 relative on a 32 px render)."""
    from drgan.core import backend

    backend.use_variant(TEST_VARIANT)
    threads = backend.dr.thread_count()
    backend.dr.set_thread_count(1)
    yield
    backend.dr.set_thread_count(threads)


@pytest.fixture(scope="session")
def tiny_scene():
    scene = make_scene()
    scene.set_layout(TINY_PHI)
    return scene


def compose(overrides=(), config_name="render"):
    """A composed config of any entry point (`drgan.launch.configs.compose`)."""
    from drgan.launch.configs import compose as drgan_compose

    return drgan_compose(overrides, config_name=config_name)
