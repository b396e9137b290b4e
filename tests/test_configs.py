"""Every config of every CLI composes, and the objects its `_target_` entries name can be built: a renamed class,
a key the class does not take or a missing group file fails here, not in a user's first run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from drgan.core.errors import ConfigError
from drgan.launch.configs import ROOTS, compose, conf_dir

# The required keys (???) of each CLI's config, filled with placeholders: composition is what is tested here.
REQUIRED = {
    "train": [],
    "render": [],
    "generate": ["ckpt=x.ckpt", "out=x"],
    "meshes": ["out=x"],
    "segment": [],
    "evaluate": [],
    "analyze": [],
    "profile": [],
    "realism": [],
    "export_nnunet": ["data=x", "out=x"],
    "import_official": ["official=x", "out=x"],
}


def group_options(group: str) -> list[str]:
    return sorted(p.stem for p in (conf_dir("gan") / group).glob("*.yaml"))


def test_every_cli_has_a_config_and_it_composes():
    names = sorted(p.stem for root in ROOTS for p in conf_dir(root).glob("*.yaml"))
    assert names == sorted(REQUIRED), "a CLI config was added or removed: list it in REQUIRED"
    for name in names:
        cfg = compose(REQUIRED[name], config_name=name)
        assert len(cfg) > 0, name


def test_segmentation_entry_points_take_data_and_model_as_plain_keys():
    """Their own config root has no `data`/`model` groups: the folder and checkpoint are plain values."""
    assert compose(["data=/some/pairs"], config_name="segment").data == "/some/pairs"
    assert compose(["data=/real", "model=a.ckpt"], config_name="evaluate").model == "a.ckpt"
    assert compose(["model=a.ckpt"], config_name="analyze").model == "a.ckpt"
    assert compose(["data=/pairs", "out=raw"], config_name="export_nnunet").data == "/pairs"
    # the shared groups reach both roots
    seg, train = compose([], config_name="segment"), compose([], config_name="train")
    assert seg.paths.log_dir == train.paths.log_dir and "mlflow" in seg.logger and "mlflow" in train.logger
    with pytest.raises(ConfigError, match="expected one of"):
        compose([], config_name="no_such_cli")


@pytest.mark.parametrize("material", group_options("material"))
def test_every_material_composes_with_the_train_config_and_resolves(material):
    cfg = compose([f"material={material}", "paths.output_dir=/tmp/drgan_cfg"], config_name="train")
    values = OmegaConf.to_container(cfg.material, resolve=True)
    assert values["name"] and values["view_width"] > 0
    OmegaConf.to_container(cfg.renderer, resolve=True)  # interpolations into the material resolve


@pytest.mark.parametrize("experiment", group_options("experiment"))
def test_every_experiment_builds_its_callbacks_and_trainer(experiment, tmp_path):
    cfg = compose([f"experiment={experiment}", f"paths.output_dir={tmp_path}", "logger=none"], config_name="train")
    callbacks = [instantiate(entry) for entry in cfg.callbacks.values() if entry is not None and "_target_" in entry]
    assert {type(c).__name__ for c in callbacks} >= {"FIDCallback", "BestEpochCallback", "FIDEarlyStopping"}
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=False)
    assert Path(trainer.default_root_dir) == tmp_path


@pytest.mark.parametrize("group", ["size", "placement", "renderer", "logger", "trainer", "debug"])
def test_every_option_of_the_train_groups_composes(group):
    for option in group_options(group):
        compose([f"{group}={option}", "paths.output_dir=/tmp/drgan_cfg"], config_name="train")


@pytest.mark.parametrize(
    "text, message",
    [
        ("renderer:\n  sppp: 4\n", "Key 'sppp' not in 'RendererSchema'"),
        ("renderer:\n  spp: many\n", "'many' of type 'str' could not be converted to Integer"),
        ("model:\n  lr_decay:\n    steps: 1.5\n", "could not be converted to Integer"),
        ("model:\n  betas: 0.5\n", "betas"),
    ],
)
def test_typed_groups_refuse_a_wrong_key_or_type_when_composing(text, message, tmp_path):
    """A user's file (here an experiment on the search path) with a typo or a wrong type fails at compose time,
    naming the key; a user's search path (which replaces the configs' own list) still finds the shared groups."""
    from hydra.errors import ConfigCompositionException

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "mine.yaml").write_text("# @package _global_\n" + text)
    overrides = ["experiment=mine", f"hydra.searchpath=[file://{tmp_path}]"]
    with pytest.raises(ConfigCompositionException, match=message):
        compose(overrides, config_name="train")
    (tmp_path / "experiment" / "mine.yaml").write_text("# @package _global_\nrenderer:\n  spp: 4\n")
    cfg = compose(overrides, config_name="train")
    assert cfg.renderer.spp == 4 and cfg.paths.log_dir and "mlflow" in cfg.logger
    with pytest.raises(ConfigCompositionException, match="Error merging override model.lr_g=fast"):
        compose(["model.lr_g=fast"], config_name="train")


def test_the_training_grid_the_profile_predicts_is_the_one_training_mines():
    """The profile counts whole particles per window on drgan.data.patches.STRIDE's grid to choose data.min_particles:
    the stride training reads from its config, and the data module's default, must be that one."""
    import inspect

    from drgan.data.datamodule import RealPatchDataModule
    from drgan.data.patches import STRIDE

    assert compose([], config_name="train").data.stride == STRIDE
    assert inspect.signature(RealPatchDataModule.__init__).parameters["stride"].default == STRIDE


def test_read_settings_types_each_key_by_its_field_and_names_the_key_it_refuses():
    """The one reader of a stage's keys: a field's type and bounds decide, an absent key takes the field's default,
    a required one is named, an empty string where null is allowed is null, a field's own check speaks for itself."""
    import dataclasses
    from pathlib import Path

    from omegaconf import OmegaConf

    from drgan.core.errors import ConfigError
    from drgan.core.typed_settings import read_settings, setting

    def even(stage, value):
        if value % 2:
            raise ConfigError(f"{stage}: odd={value}: expected an even number")
        return value // 2

    @dataclasses.dataclass(frozen=True)
    class Keys:
        folder: Path = setting()
        model: str | None = None
        bins: int = setting(30, ge=1)
        alpha: float = 0.5
        flag: bool = False
        rows: tuple[int, int] | str | None = "auto"
        names: tuple[str, ...] = ()
        odd: int = setting(4, check=even)

    cfg = OmegaConf.create({"folder": "x", "model": "", "bins": 3, "alpha": 1, "rows": [2, 5], "names": ["a", "b"],
                            "odd": 8, "unrelated": 1})  # fmt: skip
    keys = read_settings(Keys, cfg, "stage")
    assert keys == Keys(folder=Path("x"), model=None, bins=3, alpha=1.0, rows=(2, 5), names=("a", "b"), odd=4)
    assert isinstance(keys.alpha, float) and read_settings(Keys, OmegaConf.create({"folder": "y"}), "s").bins == 30
    refused = {
        "bins": (0, "stage: bins=0: expected an integer >= 1"),
        "flag": ("yes", "stage: flag='yes': expected true or false"),
        "alpha": (True, "stage: alpha=True: expected a number"),
        "rows": ([1, 2, 3], "expected a list of 2 or a string or null"),
        "names": ("a", "expected a list"),
        "odd": (3, "stage: odd=3: expected an even number"),
    }
    for key, (value, message) in refused.items():
        with pytest.raises(ConfigError, match=re.escape(message)):
            read_settings(Keys, OmegaConf.create({"folder": "x", key: value}), "stage")
    with pytest.raises(ConfigError, match=re.escape("stage: data.folder is not set")):
        read_settings(Keys, OmegaConf.create({}), "stage", prefix="data.")


def test_typed_settings_keep_their_types_where_their_module_is_not_at_hand():
    """A stage's settings classes live in its __main__ module; a sweep's worker (Hydra's joblib or submitit
    launcher) receives them by value, without that module's names: `typed` resolved the types where they were
    defined, a class without it cannot be read there."""
    import sys
    import types

    from drgan.core.typed_settings import read_settings

    source = (
        "from __future__ import annotations\nfrom dataclasses import dataclass\nfrom pathlib import Path\n"
        "from drgan.core.typed_settings import typed\n"
        "@typed\n@dataclass(frozen=True)\nclass Kept:\n    folder: Path | None = None\n"
        "@dataclass(frozen=True)\nclass Bare:\n    folder: Path | None = None\n"
    )
    module = types.ModuleType("drgan_test_sweep_main")
    sys.modules[module.__name__] = module
    try:
        exec(source, module.__dict__)
        del module.__dict__["Path"]  # the worker's view: the class without its module's names
        assert read_settings(module.Kept, {"folder": "x"}, "s").folder == Path("x")
        with pytest.raises(NameError):
            read_settings(module.Bare, {"folder": "x"}, "s")
    finally:
        del sys.modules[module.__name__]
