"""Every material config composes; `python -m drgan.render` writes image, labels, mask and params."""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import compose
from PIL import Image

from drgan.models import build

MATERIALS = ["tio2_sem", "tio2_him", "sio2_him", "agnw_sem"]
PAPER = {
    "tio2_sem": (40, 121, 0.5, 1),
    "tio2_him": (15, 16, 3.0, 4),
    "sio2_him": (20, 16, 3.0, 4),
    "agnw_sem": (10, 121, 0.5, 4),
}


@pytest.mark.parametrize("material", MATERIALS)
def test_material_configs_hold_the_papers_settings(material):
    cfg = compose([f"material={material}"])
    n, spp, stddev, contour = PAPER[material]
    assert cfg.material.n_particles == n and cfg.renderer.spp == spp
    assert cfg.material.filter_stddev == stddev and cfg.material.contour_px == contour
    assert "filter_stddev" not in cfg.renderer and "spp" not in cfg.material  # each setting in one place
    spec = build.scene_spec(cfg.material, cfg.renderer)
    assert (spec.render.spp, spec.render.filter_stddev) == (spp, stddev)
    assert [p.key for p in spec.parameters.learned] == [
        "stage.base_color",
        "particle.roughness",
        "particle.base_color",
        "particle.sheen",
        "particle.sheen_tint",
        "particle.spec_tint",
        "noise.sigma",
    ]
    phi = build.sample_phi(cfg, m=2, seed=0)
    assert phi.shape == (2, n, 4)


@pytest.mark.parametrize("material", MATERIALS)
def test_render_cli_writes_annotated_image(material, tmp_path):
    out = tmp_path / material
    cmd = [
        sys.executable,
        "-m",
        "drgan.render",
        f"material={material}",
        f"out={out}",
        "renderer.resolution=24",
        "renderer.spp=1",
        "material.meshes.count=3",
    ]
    subprocess.run(cmd, check=True, capture_output=True, cwd=tmp_path, timeout=300)
    image = np.asarray(Image.open(out / "image.png"))
    labels = np.asarray(Image.open(out / "labels.png"))
    mask = np.asarray(Image.open(out / "mask.png"))
    assert image.shape == labels.shape == mask.shape == (24, 24)
    assert set(np.unique(mask)) <= {0, 1, 2}
    np.testing.assert_array_equal(mask > 0, labels > 0)
    params = json.loads((out / "params.json").read_text())
    assert np.array(params["phi"]).shape == (PAPER[material][0], 4)
    assert "noise.sigma" in params["parameters"]


def test_render_cli_rejects_bad_spp(tmp_path):
    cmd = [sys.executable, "-m", "drgan.render", f"out={tmp_path / 'x'}", "renderer.spp=-1"]
    result = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert result.returncode != 0 and "renderer.spp=-1" in result.stderr
    assert not (tmp_path / "x" / "image.png").exists()
