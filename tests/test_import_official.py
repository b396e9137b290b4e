"""drgan.import_official: the paper's published generators (../shared/official) as drgan checkpoints.

The reference for every parameter value is the official network computed here from its state dict with plain torch
operations (w = g v / ||v||), in the official output order (stage's learned keys, particles' in the official key
order, noise sigma) and limits, read from the JSON directly.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from drgan.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
CANDIDATES = [os.environ.get("DRGAN_OFFICIAL", ""), ROOT.parent / "shared" / "official", ROOT.parents[1] / "shared" / "official"]  # fmt: skip
OFFICIAL = next((Path(c) for c in CANDIDATES if c and (Path(c) / "experiments").is_dir()), None)
needs_official = pytest.mark.skipif(OFFICIAL is None, reason="the official experiments (../shared/official) are absent")
TAGS = ("Ag_paper", "Mill2021SiO2_paper", "Mill2021TiO2_paper", "Ruehle2021TiO2_paper")
# The official generator's key order (utils/rendering/particle_scene.py): learned keys are written in this order.
OFFICIAL_ORDER = (
    "base_color", "sheen", "spec_tint", "metallic", "specular", "anisotropic", "spec_trans", "clearcoat_gloss",
    "clearcoat", "flatness", "sheen_tint", "roughness",
)  # fmt: skip


def experiment(tag: str) -> Path:
    return OFFICIAL / "experiments" / tag


def official_reference(tag: str, phi: torch.Tensor) -> torch.Tensor:
    """The official network's scene values for phi (B, n, 4), in float64, from the files alone."""
    folder = experiment(tag)
    settings = json.loads(next(folder.glob("*.json")).read_text())["scene_param_dict"]
    state = torch.load(next(folder.glob("G_*.pth")), map_location="cpu", weights_only=True)
    x = phi.reshape(phi.shape[0], -1).double()
    for layer in ("fc1", "fc2", "fc3", "fc4", "output_layer.0"):
        g, v = state[f"params_model.{layer}.weight_g"].double(), state[f"params_model.{layer}.weight_v"].double()
        x = x @ (g * v / v.norm(dim=1, keepdim=True)).T + state[f"params_model.{layer}.bias"].double()
        x = torch.sigmoid(x) if layer == "output_layer.0" else torch.relu(x)
    limits = [
        (settings[f"{kind}_limit_min"], settings[f"{kind}_limit_max"])
        for kind, prefix in (("stage_bsdf", "s"), ("particle_bsdf", "p"))
        for name in OFFICIAL_ORDER
        if settings[f"{prefix}_{name}"] < 0
    ] + [(settings["noise_limit_min"], settings["noise_limit_max"])]
    low, high = (x.new_tensor(col) for col in zip(*limits))
    return low + (high - low) * x


def layouts(cfg: dict, m: int, seed: int) -> torch.Tensor:
    from drgan.scene import layout

    size, placement = layout.size_from_config(cfg["size"]), layout.placement_from_config(cfg["placement"])
    n = cfg["material"]["n_particles"]
    return torch.as_tensor(layout.sample_layouts(m, n, size, placement, seed=seed))


@needs_official
@pytest.mark.parametrize("tag", TAGS)
def test_network_values_equal_the_official_networks(tag, tmp_path):
    """The network drgan loads (weights converted, input scaled by 1/256, limits and order of the material) gives
    the official network's values to 1e-5 on fixed constellations, for all four cases (without building scenes)."""
    from drgan import import_official as imp
    from drgan.models.regressor import ParameterRegressor
    from drgan.scene.config import typed_material

    json_path, weights_path, _ = imp.find_experiment(experiment(tag), None)
    settings, weights = imp.read_settings(json_path), imp.read_weights(weights_path)
    n = weights["params_model.fc1.weight_v"].shape[1] // 4
    frames = [[0.0, 0.0, 0.0, 1.0]]
    scene_files = {key: tmp_path / name for key, name in imp.SCENE_FILES.items()}
    cfg = imp.model_config(settings, tag, None, tmp_path, tmp_path, (frames, [None] * n), scene_files)
    material = typed_material(cfg["material"])
    learned = material.imaging.material_parameters(material.noise_sigma).learned
    regressor = ParameterRegressor(n, len(learned), hidden=cfg["model"]["hidden"], blocks=4, dropout=0.2).eval()
    regressor.load_state_dict(imp.regressor_state(weights, material.view_width))

    phi = layouts(cfg, 16, seed=3)
    phi[0] = 0.0  # and the constellation of all zeros
    low, high = torch.tensor([p.low for p in learned]), torch.tensor([p.high for p in learned])
    with torch.no_grad():
        ours = low + (high - low) * regressor(phi / material.view_width)
    torch.testing.assert_close(ours.double(), official_reference(tag, phi), rtol=0, atol=1e-5)
    assert [p.key for p in learned][-1] == "noise.sigma"


@needs_official
def test_import_writes_a_checkpoint_that_generate_uses(tmp_path):
    """The imported SiO2 HIM run: its checkpoint loads as drgan.generate loads it, gives the official values, and
    renders (tiny) images with labels."""
    from drgan import import_official as imp
    from drgan.synthetic.source import checkpoint_config, load_module

    ckpt = imp.import_experiment(experiment("Mill2021SiO2_paper"), tmp_path / "run")
    assert ckpt == tmp_path / "run" / "checkpoints" / "best.ckpt"
    assert (tmp_path / "run" / "material" / "sio2_him_paper.yaml").is_file()
    cfg = checkpoint_config(ckpt)
    cfg["renderer"].update(resolution=32, spp=1)
    module = load_module(ckpt, cfg)
    phi = torch.as_tensor(module.sample_phi(4, seed=1))
    with torch.no_grad():
        values = module.generator.learned_values(phi)
    torch.testing.assert_close(values.double(), official_reference("Mill2021SiO2_paper", phi), rtol=0, atol=1e-5)
    sample = module.generator.sample(phi[1], seed=5)
    assert sample.image.shape == (32, 32) and 0.0 <= sample.image.min() and sample.image.max() <= 1.0
    assert sample.labels.max() > 0 and (sample.labels == 0).any()


@needs_official
def test_fixed_values_are_those_the_official_scene_renders():
    """The official XML fills the particles' BSDF from the s_* keys and the stage's from the p_* keys (a learned
    key, -1, read as 0): particles get specular 0, the stage roughness 0 and specular 0.5."""
    from drgan import import_official as imp

    settings = imp.read_settings(next(experiment("Ruehle2021TiO2_paper").glob("*.json")))
    particle, stage = imp.bsdf_tables(settings["scene_param_dict"])
    assert list(particle)[:5] == ["base_color", "sheen", "spec_tint", "sheen_tint", "roughness"]
    assert particle["roughness"] == {"min": 0.01, "max": 5.0} and particle["specular"] == {"value": 0.0}
    assert stage["base_color"] == {"min": 0.01, "max": 0.4}
    assert stage["roughness"] == {"value": 0.0} and stage["specular"] == {"value": 0.5}
    assert "flatness" not in particle and "flatness" not in stage


@needs_official
def test_unknown_keys_are_errors_naming_them(tmp_path):
    from drgan import import_official as imp

    folder = tmp_path / "Ag_paper"
    shutil.copytree(experiment("Ag_paper"), folder)
    settings = json.loads((folder / "Ag_paper.json").read_text())
    settings["mesh_dict"]["mesh_rotation"] = 1.0
    (folder / "Ag_paper.json").write_text(json.dumps(settings))
    with pytest.raises(ConfigError, match="mesh_rotation"):
        imp.read_settings(folder / "Ag_paper.json")
    del settings["mesh_dict"]["mesh_rotation"]
    settings["scene_param_dict"]["p_glow"] = -1.0
    (folder / "Ag_paper.json").write_text(json.dumps(settings))
    with pytest.raises(ConfigError, match="p_glow"):
        imp.read_settings(folder / "Ag_paper.json")

    state = torch.load(folder / "G_42.pth", map_location="cpu", weights_only=True)
    state["params_model.fc5.weight"] = torch.zeros(1)
    torch.save(state, folder / "G_42.pth")
    with pytest.raises(ConfigError, match="fc5"):
        imp.read_weights(folder / "G_42.pth")


def test_official_placement_keeps_particles_apart_and_splits_agglomerates():
    from drgan.scene.placements import OfficialPlacement

    rng = np.random.default_rng(0)
    sizes = rng.lognormal(0.0, 0.2, 40)
    for position3d in (False, True):
        placement = OfficialPlacement("poisson", limit=10.0, position3d=position3d, max_agglomerates=5)
        centres = placement.sample(rng, sizes, 256.0)
        gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1) - (sizes[:, None] + sizes[None])
        assert (gaps[~np.eye(40, dtype=bool)] > -1e-9).all()
        assert position3d or (centres[:, 2] == 0).all()
    random = OfficialPlacement("random", limit=4.0).sample(rng, sizes[:10], 256.0)
    assert (np.abs(random[:, :2]) <= 4.0).all() and (random[:, 2] == 0).all()
    with pytest.raises(ConfigError, match="max_agglomerates"):
        OfficialPlacement("poisson", max_agglomerates=3).sample(rng, sizes[:10], 256.0)
    with pytest.raises(ConfigError, match="algorithm"):
        OfficialPlacement("grid")
