"""One typed source per setting: the renderer group's keys are `RenderSettings`' fields.

`drgan.launch.configs.renderer_schema` derives the compose-time schema from `drgan.scene.render_settings.RenderSettings`
(CONTRIBUTING.md, "Configs"), so a renderer key is declared once (type, default, check) and the YAML line that shows
it to users must say the same default: checked here, together with what adding a field does, from compose to the
built settings, with nothing but the field."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import typing
from dataclasses import dataclass

import pytest
from omegaconf import OmegaConf

from drgan.core.errors import ConfigError
from drgan.launch import configs
from drgan.launch.configs import compose, conf_dir
from drgan.scene.render_settings import RenderSettings, renderer_fields

DEFAULT_YAML = conf_dir("gan") / "renderer" / "default.yaml"


def schema_defaults(schema: type) -> dict:
    return {f.name: f.default for f in dataclasses.fields(schema)}


def yaml_drift(text: str) -> list[str]:
    """Each literal value of a renderer preset's text that differs from the schema's default (which is RenderSettings'
    for all but ``variant``), or names a key the schema lacks; interpolations (``${material.view_width}``) are left
    out, they are the material's."""
    node = OmegaConf.create(text)
    defaults = schema_defaults(configs.renderer_schema())
    drift = []
    for key in node:
        if key == "defaults" or OmegaConf.is_interpolation(node, key):
            continue
        if key not in defaults:
            drift.append(f"{key}: not a renderer key")
        elif node[key] != defaults[key] or type(node[key]) is not type(defaults[key]):
            drift.append(f"{key}: {node[key]!r} in the YAML, {defaults[key]!r} in RenderSettings")
    return drift


def test_the_renderer_yaml_says_the_render_settings_defaults():
    """Every literal value of conf/gan/renderer/default.yaml is RenderSettings' default (``variant``: the schema's
    ``auto``), so the line a user reads and the value a key without a line gets never drift apart."""
    text = DEFAULT_YAML.read_text()
    assert yaml_drift(text) == []
    node = OmegaConf.load(DEFAULT_YAML)
    literal = [k for k in node if k != "defaults" and not OmegaConf.is_interpolation(node, k)]
    assert len(literal) >= 7 and [k for k in node if OmegaConf.is_interpolation(node, k)] == ["resolution"]
    # the check sees a drifted line (the test can fail), a key the settings lack, and a mistyped default
    assert yaml_drift(text.replace("spp: 16 ", "spp: 36 ")) == ["spp: 36 in the YAML, 16 in RenderSettings"]
    assert yaml_drift(text + "sppp: 4\n") == ["sppp: not a renderer key"]
    assert yaml_drift(text.replace("camera_distance: 10.0", "camera_distance: 10")) == [
        "camera_distance: 10 in the YAML, 10.0 in RenderSettings"
    ]


def test_the_renderer_schema_is_render_settings_plus_the_variant():
    """The schema's keys are `variant` and RenderSettings' renderer fields in their order (the order a composed config
    lists them); each Optional with RenderSettings' default; generate's all null. ``filter_stddev`` is a field but the
    material's (the instrument's blur), so no renderer key."""
    schema, overrides = configs.renderer_schema(), configs.renderer_schema(overrides=True)
    keys = [f.name for f in renderer_fields()]
    assert "filter_stddev" not in keys and "filter_stddev" in {f.name for f in dataclasses.fields(RenderSettings)}
    assert [f.name for f in dataclasses.fields(schema)] == ["variant", *keys]
    assert [f.name for f in dataclasses.fields(overrides)] == ["variant", *keys]
    assert schema_defaults(schema) == {"variant": "auto", **{f.name: f.default for f in renderer_fields()}}
    assert set(schema_defaults(overrides).values()) == {None}
    hints = typing.get_type_hints(schema)
    assert hints["spp"] == typing.Optional[int] and hints["grad_spp"] == typing.Optional[int]  # noqa: UP045
    assert hints["camera_distance"] == typing.Optional[float]  # noqa: UP045
    cfg = compose(["material=tio2_sem"], config_name="render")
    assert list(cfg.renderer) == ["variant", *keys] and "filter_stddev" not in cfg.renderer
    assert OmegaConf.to_container(compose(["ckpt=x"], config_name="generate").renderer) == dict.fromkeys(
        ["variant", *keys]
    )


def test_composing_a_config_does_not_start_the_renderer():
    """RenderSettings lives apart from the scene (drgan.scene.render_settings) so that composing, which every stage
    and the pipeline's check does, neither imports Mitsuba nor torch."""
    code = (
        "import sys\n"
        "from drgan.launch.configs import compose\n"
        "compose(['renderer=sem'], config_name='train')\n"
        "print(sorted(m for m in ('mitsuba', 'drjit', 'torch', 'drgan.scene.scene') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]", out


# -- a toy renderer key, added here only ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ToySettings(RenderSettings):
    """`RenderSettings` with one more key, as a new key is added: a field with its default, and its check."""

    toy: int = 0  # the toy key (>= 0); no YAML line

    def __post_init__(self):
        super().__post_init__()
        if self.toy < 0:
            raise ConfigError(f"renderer.toy={self.toy}: expected >= 0")


def test_a_new_renderer_key_is_one_field_of_render_settings(monkeypatch):
    """CONTRIBUTING.md, "a setting of the renderer": a field of RenderSettings (here a subclass put in its place, so
    nothing persists) is a renderer key with nothing else changed (configs.py, the YAML): it composes with its default
    where no YAML line gives it, takes ``renderer.toy=3``, is an override of generate's, a wrong type fails at compose
    naming the key, and a value its check refuses fails when the settings are built."""
    from hydra.errors import ConfigCompositionException

    from drgan.models import build
    from drgan.scene.config import typed_material

    def settings(overrides):
        cfg = compose(overrides, config_name="render")
        return build.render_settings(typed_material(cfg.material), cfg.renderer)

    try:
        monkeypatch.setattr("drgan.scene.render_settings.RenderSettings", ToySettings)
        monkeypatch.setattr("drgan.scene.scene.RenderSettings", ToySettings)  # what drgan.models.build reads
        assert compose([], config_name="render").renderer.toy == 0
        assert compose(["renderer.toy=3"], config_name="render").renderer.toy == 3
        assert compose(["renderer=sem", "renderer.toy=3"], config_name="train").renderer.toy == 3
        assert compose(["ckpt=x"], config_name="generate").renderer.toy is None
        assert compose(["ckpt=x", "renderer.toy=5"], config_name="generate").renderer.toy == 5
        built = settings(["renderer.toy=3", "renderer.spp=4"])
        assert isinstance(built, ToySettings) and (built.toy, built.spp) == (3, 4)
        with pytest.raises(ConfigCompositionException) as error:
            compose(["renderer.toy=many"], config_name="render")
        assert "toy" in str(error.value.__cause__ or error.value)
        with pytest.raises(ConfigError, match=r"renderer\.toy=-1: expected >= 0"):
            settings(["renderer.toy=-1"])
    finally:
        monkeypatch.undo()
        configs.setup()  # the ConfigStore's renderer schemas back to drgan's own
    with pytest.raises(ConfigCompositionException, match="Could not override 'renderer.toy'"):
        compose(["renderer.toy=3"], config_name="render")  # without the field, the key is unknown again
