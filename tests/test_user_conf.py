"""Users' own configs: a material in ./drgan_conf found from the folder drgan runs in, inheriting a paper material."""

from __future__ import annotations

import textwrap

import pytest
from conftest import compose

from drgan.core.errors import ConfigError
from drgan.models.build import scene_spec
from drgan.scene.config import typed_material


def write_material(root, name, body):
    folder = root / "drgan_conf" / "material"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.yaml").write_text(textwrap.dedent(body))


def test_a_user_material_inherits_a_paper_material_and_fixes_one_learned_parameter(tmp_path, monkeypatch):
    write_material(
        tmp_path,
        "my_tio2",
        """\
        # @package _global_
        defaults:
          - tio2_sem
        material:
          name: my_tio2
          n_particles: 12
          imaging:
            particle_bsdf:
              sheen: {value: 0.0}
        """,
    )
    monkeypatch.chdir(tmp_path)
    cfg = compose(["material=my_tio2"], config_name="train")
    assert cfg.material.name == "my_tio2" and cfg.material.n_particles == 12
    params = {p.key: p for p in scene_spec(cfg.material, cfg.renderer).parameters.bsdf}
    assert params["particle.sheen"].value == 0.0 and not params["particle.sheen"].learned
    assert params["particle.roughness"].learned  # the rest stays as inherited
    assert (params["particle.roughness"].low, params["particle.roughness"].high) == (0.01, 5.0)


def test_a_parameter_with_value_and_stray_keys_is_still_refused():
    cfg = compose(["material=tio2_sem"], config_name="render")
    material = typed_material(cfg.material)  # a valid material, then one stray key in a parameter
    saved = {
        **vars(material),
        "imaging": {"_target_": material.imaging._target_, "particle_bsdf": {"sheen": {"value": 0.0, "mean": 1.0}}},
    }
    with pytest.raises(
        ConfigError, match=r"material\.imaging\.particle_bsdf\.sheen: expected keys .*got \[.mean., .value.\]"
    ):
        typed_material(saved)


def test_render_finds_a_user_material_too(tmp_path, monkeypatch):
    write_material(
        tmp_path,
        "my_render",
        """\
        # @package _global_
        defaults:
          - sio2_him
        material:
          name: my_render
        """,
    )
    monkeypatch.chdir(tmp_path)
    cfg = compose(["material=my_render"], config_name="render")
    assert cfg.material.name == "my_render" and cfg.material.meshes.kind == "sphere"
