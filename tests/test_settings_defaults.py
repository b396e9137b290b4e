"""One default per setting: where a stage's YAML shows a key's value, it is the default of the settings field that
reads it (`drgan.core.typed_settings.read_settings`), so a key left out of a saved config (an older run's, a
resumed or fine-tuned base) gets the value the YAML tells users. The renderer's keys have their own check
(test_settings_source.py)."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
from omegaconf import DictConfig, ListConfig, OmegaConf

from drgan.analyze import AnalyzeSettings
from drgan.evaluate import EvaluateSettings, _Runs
from drgan.export_nnunet import ExportSettings
from drgan.launch.configs import compose
from drgan.models.gan_module import GANTraining, LRDecay
from drgan.pipeline.settings import CONFIG as PIPELINE_YAML
from drgan.pipeline.settings import _OwnKeys
from drgan.profile import ProfileData, ProfileSettings
from drgan.realism import RealismSettings, RenderKeys
from drgan.segment import SegmentRun
from drgan.segmenters.agreement import AgreementSettings
from drgan.segmenters.training import LoaderSettings, TrainingPairs, _HeldOut, _Source
from drgan.synthetic.generation_settings import GenerateSettings
from drgan.train import TrainRun

SRC = Path(__file__).resolve().parents[1] / "src" / "drgan"
# (settings class, config name, the node its keys sit under)
READERS = [
    (SegmentRun, "segment", ""), (_Source, "segment", ""), (TrainingPairs, "segment", ""),
    (LoaderSettings, "segment", "loader"), (_HeldOut, "segment", ""), (AgreementSettings, "segment", "agreement"),
    (EvaluateSettings, "evaluate", ""), (_Runs, "evaluate", ""), (AnalyzeSettings, "analyze", ""),
    (ProfileData, "profile", "data"), (ProfileSettings, "profile", ""), (ExportSettings, "export_nnunet", ""),
    (RealismSettings, "realism", ""), (RenderKeys, "realism", "render"), (GenerateSettings, "generate", ""),
    (LRDecay, "train", "model.lr_decay"), (GANTraining, "train", "model"), (TrainRun, "train", ""),
    (_OwnKeys, "pipeline", ""),
]  # fmt: skip
# a field whose default is, on purpose, not the YAML's value, and why
DIFFERENT = {("_HeldOut", "check_fraction"): "a saved config without the key is a run from before the check: none"}


def defaults(cls: type) -> dict:
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


def node_of(config: str, path: str):
    if config == "pipeline":
        return OmegaConf.load(PIPELINE_YAML)
    cfg = compose([], config_name=config)
    return OmegaConf.select(cfg, path) if path else cfg


def same(yaml_value, default) -> bool:
    if isinstance(default, tuple) and isinstance(yaml_value, list):
        return list(default) == yaml_value
    if isinstance(default, Path) and isinstance(yaml_value, str):
        return default == Path(yaml_value)
    if isinstance(default, bool) or isinstance(yaml_value, bool):
        return yaml_value is default
    return yaml_value == default and (type(yaml_value) is type(default) or isinstance(default, float))


def drift(cls: type, node) -> list[str]:
    """Each scalar key of ``node`` that a field of ``cls`` reads with another default (mappings are typed by classes
    of their own; interpolations and required fields have no default to compare)."""
    found = []
    for name, default in defaults(cls).items():
        if node is None or name not in node or OmegaConf.is_interpolation(node, name):
            continue
        value = node[name]
        if isinstance(value, (DictConfig, ListConfig)):
            value = OmegaConf.to_container(value, resolve=True)
            if isinstance(value, dict):
                continue
        if not same(value, default) and (cls.__name__, name) not in DIFFERENT:
            found.append(f"{cls.__name__}.{name}: {value!r} in the YAML, {default!r} in the field")
    return found


@pytest.mark.parametrize("cls,config,path", READERS, ids=[r[0].__name__ for r in READERS])
def test_the_yaml_shows_the_default_of_the_field_that_reads_it(cls, config, path):
    node = node_of(config, path)
    assert drift(cls, node) == []
    assert any(name in node for name in defaults(cls)) or not defaults(cls)  # the class reads this node


def test_the_drift_check_sees_a_changed_value_and_a_changed_type():
    node = OmegaConf.create({"steps": 300, "final_factor": 0.1, "start_step": None})
    assert drift(LRDecay, node) == []
    assert drift(LRDecay, OmegaConf.merge(node, {"steps": 30})) == ["LRDecay.steps: 30 in the YAML, 300 in the field"]
    assert drift(LRDecay, OmegaConf.merge(node, {"final_factor": 1})) == [
        "LRDecay.final_factor: 1 in the YAML, 0.1 in the field"
    ]


def test_every_typed_settings_class_is_checked():
    """A new `@typed` settings class joins READERS (or the check would not see its defaults drift)."""
    typed = set()
    for path in SRC.rglob("*.py"):
        typed |= set(re.findall(r"^@typed\n(?:@dataclass[^\n]*\n)+class (\w+)", path.read_text(), re.M))
    assert typed and typed <= {cls.__name__ for cls, _, _ in READERS}, typed - {cls.__name__ for cls, _, _ in READERS}
