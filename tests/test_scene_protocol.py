"""The seams of drgan's scenes and materials: a typed material checked at compose time, a scene registry that a
new imaging mode joins without touching drgan, and a package whose import changes nothing and has no cycles."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import compose
from omegaconf import MISSING, OmegaConf
from test_train import SIZE, run_train, tiny_overrides

from drgan.core.errors import ConfigError
from drgan.scene.config import ImagingConfig, Material, ParameterRange, register_scene, typed_material
from drgan.scene.parameters import parse_parameter
from drgan.scene.scene import MeshParticles, reconstruction_blur


# -- a toy imaging mode, defined here only ------------------------------------------------------------------
@dataclass
class SilhouetteImaging(ImagingConfig):
    """Flat silhouettes: every particle pixel one grey, every other pixel another."""

    _target_: str = f"{__name__}.SilhouetteScene"
    background: ParameterRange = MISSING
    particle: ParameterRange = MISSING

    def scene_parameters(self):
        return tuple(
            parse_parameter("silhouette", name, getattr(self, name), f"material.imaging.{name}")
            for name in ("background", "particle")
        )


@dataclass(frozen=True)
class SilhouetteSpec:
    parameters: object
    render: object
    view_width: float


@register_scene
class SilhouetteScene(MeshParticles):
    Config = SilhouetteImaging

    @classmethod
    def spec_from_config(cls, material, render):
        return SilhouetteSpec(material.imaging.material_parameters(material.noise_sigma), render, material.view_width)

    def _scene_dict(self) -> dict:
        return {"type": "scene", "sensor": self._sensor_dict(), "particles": self.particles}

    @property
    def learned(self):
        return self.spec.parameters.learned_bsdf

    def render(self, values, seed, spp=None):
        del seed, spp  # no sampling: the silhouette is the label image
        given = iter(values)
        grey = {p.name: next(given) if p.learned else values.new_tensor(p.value) for p in self.spec.parameters.bsdf}
        inside = torch.from_numpy(self.instance_labels() > 0).to(values.dtype)
        image = grey["background"] + (grey["particle"] - grey["background"]) * inside
        return reconstruction_blur(image, self.spec.render.filter_stddev)


TOY_MATERIAL = f"""\
# @package _global_
defaults:
  - /drgan_schema/material@material
material:
  name: silhouettes
  polarity: bright
  n_particles: 3
  particle_size_px: 8
  view_width: 96
  meshes: {{kind: sphere, count: 1}}
  noise_sigma: {{min: 0.001, max: 0.05}}
  imaging:
    _target_: {__name__}.SilhouetteScene
    background: {{min: 0.0, max: 0.4}}
    particle: {{min: 0.5, max: 1.0}}
"""


def write_material(root, name: str, text: str) -> None:
    folder = root / "drgan_conf" / "material"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.yaml").write_text(textwrap.dedent(text))


def test_a_new_imaging_mode_is_a_scene_class_and_a_material(tmp_path, monkeypatch):
    """The toy mode above, registered here, renders through drgan's generator: background and particle greys come
    from the FCN within the material's limits, labels are exact, and the gradient reaches the FCN."""
    from drgan.models import build

    write_material(tmp_path, "silhouettes", TOY_MATERIAL)
    monkeypatch.chdir(tmp_path)
    cfg = compose(["material=silhouettes", "renderer.resolution=24", "renderer.spp=1"], config_name="render")
    generator = build.build_generator(cfg, seed=0)
    assert isinstance(generator.scene, SilhouetteScene)
    assert [p.key for p in generator.learned] == ["silhouette.background", "silhouette.particle", "noise.sigma"]
    phi = build.sample_phi(cfg, 1, seed=0)[0]
    sample = generator.sample(phi, seed=3)
    values = sample.parameters
    assert 0.0 <= values["silhouette.background"] <= 0.4 and 0.5 <= values["silhouette.particle"] <= 1.0
    inside, outside = sample.image[sample.labels > 0], sample.image[sample.labels == 0]
    assert inside.size and outside.size and inside.mean() > outside.mean() + 0.2
    images, _ = generator.render_batch(torch.as_tensor(phi)[None])
    images.mean().backward()
    grads = [p.grad for p in generator.regressor.parameters() if p.grad is not None]
    assert grads and any(float(g.abs().sum()) > 0 for g in grads)


def test_a_new_imaging_mode_trains_a_step(tmp_path, monkeypatch):
    from test_train import make_images

    images = make_images(tmp_path / "real" / "images")
    write_material(tmp_path, "silhouettes", TOY_MATERIAL)
    monkeypatch.chdir(tmp_path)
    overrides = tiny_overrides(images, tmp_path / "run", "silhouettes", extra=["trainer.fast_dev_run=1"])
    metrics = run_train([*overrides, f"material.view_width={SIZE}"])
    assert math.isfinite(metrics["train/g_loss"]) and math.isfinite(metrics["train/d_loss"])


def test_a_misspelt_or_mistyped_material_key_fails_at_compose_naming_it(tmp_path, monkeypatch):
    from hydra.errors import ConfigCompositionException

    for name, body, key in (
        ("misspelt", "n_particles_mn: 8", "n_particles_mn"),
        ("mistyped", "n_particles: many", "n_particles"),
        ("misspelt_light", "imaging:\n    torus_lihgt: {radiance: 2.0}", "torus_lihgt"),
    ):
        write_material(
            tmp_path, name, f"# @package _global_\ndefaults:\n  - tio2_sem\nmaterial:\n  name: {name}\n  {body}\n"
        )
        monkeypatch.chdir(tmp_path)
        with pytest.raises(ConfigCompositionException) as error:
            compose([f"material={name}"], config_name="train")
        assert key in str(error.value.__cause__ or error.value), (name, str(error.value))


def test_a_saved_material_is_checked_too_and_names_only_registered_scenes():
    saved = OmegaConf.to_container(compose(["material=tio2_sem"]).material, resolve=True)  # as a checkpoint holds it
    assert typed_material(saved).imaging.stage_bsdf["base_color"]["max"] == 0.4
    with pytest.raises(ConfigError, match=r"material\.imaging\._target_='os\.system': not a registered scene class"):
        typed_material({**saved, "imaging": {"_target_": "os.system"}})
    with pytest.raises(ConfigError, match=r"material\.n_particles_mn"):
        typed_material({**saved, "n_particles_mn": 3})
    with pytest.raises(ConfigError, match=r"material\.polarity='grey'"):
        typed_material({**saved, "polarity": "grey"})
    with pytest.raises(ConfigError, match=r"material\.imaging\.background: .*missing"):
        typed_material({**saved, "imaging": {"_target_": SilhouetteImaging._target_}})


def test_a_scene_class_without_its_config_is_not_registered():
    class NoConfig(MeshParticles):
        pass

    with pytest.raises(ConfigError, match="expected a Config dataclass"):
        register_scene(NoConfig)

    class WrongTarget(SilhouetteScene):
        Config = SilhouetteImaging  # its _target_ names SilhouetteScene, not WrongTarget

    with pytest.raises(ConfigError, match="defaults to"):
        register_scene(WrongTarget)


# -- the package's imports -------------------------------------------------------------------------------
def test_importing_drgan_changes_no_global_state():
    """No Hydra, OmegaConf resolver or Mitsuba on import: a label helper imports numpy and scipy, not a config
    system."""
    code = (
        "import sys, drgan, drgan.scene.labels, drgan.core.errors\n"
        "heavy = sorted(m for m in ('hydra', 'mitsuba', 'drjit', 'lightning', 'torch') if m in sys.modules)\n"
        "from omegaconf import OmegaConf\n"
        "print(heavy, OmegaConf.has_resolver('mul'))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[] False", out


def test_no_two_modules_import_each_other():
    """No import cycle in drgan (grimp, import-linter's graph: imports inside functions count too)."""
    import grimp

    graph = grimp.build_graph("drgan")
    cycles = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            if imported != module and graph.chain_exists(importer=imported, imported=module):
                cycles.append((module, imported))
    assert not cycles, cycles


def test_every_module_has_a_name_of_its_own_and_none_is_over_600_lines():
    """A module's file name says which one it is (no scene/layout.py beside a dataset/layout.py, no data/profile.py
    beside the profile stage): no two modules under src/drgan share a stem (``__init__``/``__main__`` aside); and no
    file grows past 600 lines (split it by responsibility instead)."""
    package = Path(__file__).resolve().parents[1] / "src" / "drgan"
    files = sorted(p for p in package.rglob("*.py") if "__pycache__" not in p.parts)
    stems = Counter(p.stem for p in files if p.stem not in ("__init__", "__main__"))
    shared = {s: [p.relative_to(package).as_posix() for p in files if p.stem == s] for s, n in stems.items() if n > 1}
    assert not shared, shared
    lines = {p.relative_to(package).as_posix(): len(p.read_text().splitlines()) for p in files}
    long = {name: n for name, n in lines.items() if n > 600}
    assert len(lines) > 80 and not long, long


def test_the_scene_protocol_is_what_both_scenes_implement(tiny_scene):
    from test_transmission import make_scene as transmission_scene

    from drgan.scene.protocol import Scene

    phi = np.array([[0.0, 0.0, 0.0, 20.0], [0.0, 0.0, 0.0, 0.0]], np.float32)  # one particle in the middle
    for scene in (tiny_scene, transmission_scene(n=2, resolution=16, spp=1)):
        assert isinstance(scene, Scene), type(scene)
        if scene is not tiny_scene:
            scene.set_layout(phi)
            labels = scene.instance_labels()
            assert labels[8, 8] == 1 and labels[0, 0] == 0 and set(np.unique(labels)) == {0, 1}
            image = scene.render(torch.tensor([0.9, 0.5, 0.05]), seed=0)  # background, absorption, floor
            assert image.shape == (16, 16) and image[8, 8] < image[0, 0]  # dark particle, bright film
    assert not isinstance(object(), Scene)


def test_an_installed_package_adds_an_imaging_mode_through_an_entry_point(tmp_path, monkeypatch):
    """A scene class declared as an entry point (group drgan.scenes) is found by every command, as configs saved in
    checkpoints need; other entry points are not imported."""
    from importlib.metadata import EntryPoint

    from drgan.scene import config

    (tmp_path / "plugin_scene.py").write_text(
        "from dataclasses import dataclass\n\n"
        "from test_scene_protocol import SilhouetteImaging, SilhouetteScene\n\n\n"
        "@dataclass\nclass PluginImaging(SilhouetteImaging):\n    _target_: str = 'plugin_scene.PluginScene'\n\n\n"
        "class PluginScene(SilhouetteScene):\n    Config = PluginImaging\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    points = [
        EntryPoint("other", "never_imported_scene:Scene", config.ENTRY_POINT_GROUP),
        EntryPoint("plugin", "plugin_scene:PluginScene", config.ENTRY_POINT_GROUP),
    ]
    monkeypatch.setattr("importlib.metadata.entry_points", lambda group: [p for p in points if p.group == group])
    assert "plugin_scene.PluginScene" in config.registered_scenes()
    saved = OmegaConf.to_container(compose(["material=tio2_sem"]).material, resolve=True)
    plugin = {"_target_": "plugin_scene.PluginScene", "background": {"value": 0.1}, "particle": {"min": 0.5, "max": 1}}
    material = typed_material({**saved, "imaging": plugin})
    assert type(material.imaging).__name__ == "PluginImaging"
    assert config.scene_class("plugin_scene.PluginScene").__name__ == "PluginScene"
    assert "never_imported_scene" not in sys.modules


def test_configs_name_only_allowed_classes_wherever_they_build_objects():
    """Size, placement and discriminator come from `_target_` configs through one allow-listed builder: a foreign
    class is refused before it is imported or called, a misspelt field is named with the valid ones, and the
    class's own check keeps its message."""
    from drgan.models.build import build_discriminator
    from drgan.models.discriminator import PatchDiscriminator
    from drgan.scene.layout import size_from_config

    model = compose(["material=tio2_sem"]).model
    assert isinstance(build_discriminator(model), PatchDiscriminator)
    with pytest.raises(
        ConfigError, match=r"model\.discriminator\._target_ must be one of .*PatchDiscriminator.*'os\.system'"
    ):
        build_discriminator({"discriminator": {"_target_": "os.system", "filters": 8}})
    with pytest.raises(ConfigError, match=r"unknown field\(s\) \['filter'\]; expected some of .*'filters'"):
        build_discriminator(
            {"discriminator": {"_target_": "drgan.models.discriminator.PatchDiscriminator", "filter": 8}}
        )
    with pytest.raises(ConfigError, match=r"size\.median\._target_: a value here cannot name a class"):
        size_from_config(
            {"_target_": "drgan.scene.sizes.LognormalSize", "median": {"_target_": "os.system"}, "sigma": 0.2}
        )
    with pytest.raises(ConfigError, match=r"LognormalSize\.sigma must be > 0"):
        size_from_config({"_target_": "drgan.scene.sizes.LognormalSize", "median": 20.0, "sigma": -1.0})


def test_parameter_limits_are_checked_before_anything_is_built_and_may_come_from_the_command_line():
    """Limits are typed loosely (OmegaConf refuses command-line mappings and numbers in structured values), so
    `typed_material` checks every one of them, naming it."""
    cfg = compose(["+material.imaging.particle_bsdf.metallic={min:0.1,max:0.5}", "material.noise_sigma=0.05"])
    material = typed_material(cfg.material)
    learned = [p.key for p in material.imaging.material_parameters(material.noise_sigma).learned]
    assert learned[-1] == "particle.metallic" and "noise.sigma" not in learned  # a bare number: fixed
    for override, message in (
        ("material.imaging.particle_bsdf.sheen.min=low", r"sheen\.min='low': expected a finite number"),
        ("material.imaging.particle_bsdf.sheen.min=9", r"sheen: min=9\.0 > max=5\.0"),
        ("+material.imaging.particle_bsdf.shine={value:1}", r"particle_bsdf\.shine: unknown Principled-BSDF"),
    ):
        with pytest.raises(ConfigError, match=message):
            typed_material(compose([override]).material)


# -- a toy material key, added here only ----------------------------------------------------------------------
@dataclass
class GainMaterial(Material):
    """`Material` with one more key, as a new key is added: a field with its default, and its check."""

    silhouette_gain: float = 1.0  # the toy key: how much brighter than asked the particles are (> 0)

    def __post_init__(self):
        super().__post_init__()
        if not (math.isfinite(self.silhouette_gain) and self.silhouette_gain > 0):
            raise ConfigError(f"material.silhouette_gain={self.silhouette_gain}: expected a finite number > 0")


def test_a_new_material_key_is_a_field_of_the_typed_material(tmp_path, monkeypatch):
    """CONTRIBUTING.md, "a material": a new key is a field of drgan.scene.config.Material (here a subclass put in its
    place, so nothing persists). The compose-time schema (drgan.launch.configs.schemas) and typed_material both read that
    one class: a material file's value reaches the scene, its default fills a file without it, a mistyped value
    fails at compose naming the key, and a value its check refuses fails before a scene is built."""
    from hydra.errors import ConfigCompositionException

    from drgan.launch import configs
    from drgan.models import build

    seen = []
    original = SilhouetteScene.spec_from_config.__func__

    def spec_from_config(cls, material, render):
        seen.append(material.silhouette_gain)
        return original(cls, material, render)

    monkeypatch.chdir(tmp_path)
    for name, value in (("gain", "0.5"), ("mistyped_gain", "loud"), ("refused_gain", "-1.0")):
        write_material(
            tmp_path, name, TOY_MATERIAL.replace("name: silhouettes", f"name: {name}\n  silhouette_gain: {value}")
        )
    write_material(tmp_path, "silhouettes", TOY_MATERIAL)
    try:
        monkeypatch.setattr("drgan.scene.config.Material", GainMaterial)
        monkeypatch.setattr(SilhouetteScene, "spec_from_config", classmethod(spec_from_config))
        overrides = ["renderer.resolution=24", "renderer.spp=1"]
        cfg = compose(["material=gain", *overrides], config_name="render")
        assert isinstance(build.build_scene(cfg), SilhouetteScene) and seen == [0.5]
        assert typed_material(compose(["material=silhouettes", *overrides]).material).silhouette_gain == 1.0
        with pytest.raises(ConfigCompositionException) as error:
            compose(["material=mistyped_gain", *overrides])
        assert "silhouette_gain" in str(error.value.__cause__ or error.value)
        with pytest.raises(ConfigError, match=r"material\.silhouette_gain=-1\.0: expected a finite number > 0"):
            build.build_scene(compose(["material=refused_gain", *overrides]))
    finally:
        monkeypatch.undo()
        configs.setup()  # the ConfigStore's material schema back to drgan's own
    with pytest.raises(ConfigCompositionException):  # without the field, the key is unknown again
        compose(["material=gain"])
