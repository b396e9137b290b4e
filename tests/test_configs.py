"""Every config of every CLI composes, and the objects its `_target_` entries name can be built: a renamed class,
a key the class does not take or a missing group file fails here, not in a user's first run."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from drgan.configs import compose, conf_dir

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
}


def group_options(group: str) -> list[str]:
    return sorted(p.stem for p in (conf_dir() / group).glob("*.yaml"))


def test_every_cli_has_a_config_and_it_composes():
    names = sorted(p.stem for p in conf_dir().glob("*.yaml"))
    assert names == sorted(REQUIRED), "a CLI config was added or removed: list it in REQUIRED"
    for name in names:
        if name == "export_nnunet":  # its `data` key shares a name with train's group: composed from its own file
            from drgan.export_nnunet import compose_config

            cfg = compose_config(REQUIRED[name])
        else:
            cfg = compose(REQUIRED[name], config_name=name)
        assert len(cfg) > 0, name


@pytest.mark.parametrize("material", group_options("material"))
def test_every_material_composes_with_the_train_config_and_resolves(material):
    cfg = compose([f"material={material}", "paths.output_dir=/tmp/drgan_cfg"], config_name="train")
    values = OmegaConf.to_container(cfg.material, resolve=True)
    assert values["name"] and values["view_width"] > 0
    OmegaConf.to_container(cfg.renderer, resolve=True)  # interpolations into the material resolve


@pytest.mark.parametrize("experiment", group_options("experiment"))
def test_every_experiment_builds_its_callbacks_and_trainer(experiment, tmp_path):
    cfg = compose([f"experiment={experiment}", f"paths.output_dir={tmp_path}", "logger=none"], config_name="train")
    callbacks = [instantiate(entry) for entry in cfg.callbacks.values() if "_target_" in entry]
    assert {type(c).__name__ for c in callbacks} >= {"FIDCallback", "BestEpochCallback", "FIDEarlyStopping"}
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=False)
    assert Path(trainer.default_root_dir) == tmp_path


@pytest.mark.parametrize("group", ["size", "placement", "renderer", "logger", "trainer", "debug"])
def test_every_option_of_the_train_groups_composes(group):
    for option in group_options(group):
        compose([f"{group}={option}", "paths.output_dir=/tmp/drgan_cfg"], config_name="train")
