"""The segmenter seam: segmenters built from `_target_` configs, checkpoints rebuilt only from the allow-list
(drgan.segmenters.registry), and one loader from what a user names (a checkpoint, or a folder of predicted masks
such as nnU-Net's output) to class maps (drgan.segmenters.predictors), used by evaluate and analyze.

Masks are written by hand with numpy and PIL; their scores are counted by hand in the docstrings.
"""

from __future__ import annotations

import csv
import json
import re
import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import lightning.pytorch as L
import numpy as np
import pytest
import torch
from conftest import compose
from PIL import Image
from test_segment import disc_image, disc_labels, eval_cfg, make_real

from drgan.core.errors import ConfigError, DataError
from drgan.core.targets import target_path
from drgan.segmenters import registry
from drgan.segmenters.module import SegmenterModule

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TARGET = "drgan.segmenters.module.SegmenterModule"
TINY = ["model.depth=2", "model.base=4", "model.contact_weight=0"]  # auto is drgan.segment's to resolve


class TinySegmenter(SegmenterModule):
    """A segmenter class outside drgan, registered by the tests that use it."""


class Forgetful(L.LightningModule):
    """Registered but does not save its hyperparameters: its checkpoints could not be rebuilt."""

    def __init__(self, width: int = 1):
        super().__init__()
        self.net = torch.nn.Conv2d(1, 3, width)


@pytest.fixture
def own_registry(monkeypatch):
    """A copy of the allow-list, so that classes registered by a test leave with it."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    return registry


def save_checkpoint(path: Path, hparams: dict, state_dict: dict | None = None) -> Path:
    """What Lightning writes, as far as loading reads it: the weights and the hyperparameters."""
    torch.save({"state_dict": state_dict or {}, "hyper_parameters": hparams}, path)
    return path


def tiny_model(*extra) -> SegmenterModule:
    return registry.build_segmenter(compose([*TINY, *extra], config_name="segment").model)


# --- segmenters from _target_ configs ------------------------------------------------------------------------


def test_segment_config_builds_its_model_with_instantiate():
    from hydra.utils import instantiate

    cfg = compose([*TINY, "model.normalize=zscore"], config_name="segment")
    assert cfg.model._target_ == TARGET == target_path(SegmenterModule)
    assert type(instantiate(cfg.model)) is SegmenterModule  # a plain Hydra _target_ node
    model = registry.build_segmenter(cfg.model)
    assert type(model) is SegmenterModule and model.input_normalization == "zscore"
    assert model.hparams["_target_"] == TARGET and model.hparams["depth"] == 2 and model.hparams["base"] == 4
    assert TARGET in registry.registered_segmenters()


@pytest.mark.parametrize(
    "target, message",
    [
        (
            "torch.nn.Identity",
            "model: _target_ 'torch.nn.modules.linear.Identity' is not an allowed segmenter (given as",
        ),
        ("no_such_package.Net", "model._target_=no_such_package.Net: no such class"),
    ],
)
def test_segment_refuses_a_target_outside_the_allow_list_before_reading_data(target, message, tmp_path):
    from drgan.segment import segment

    out = tmp_path / "run"
    cfg = compose([f"model._target_={target}", f"data={tmp_path}", f"out={out}", "logger=none"], config_name="segment")
    with pytest.raises(ConfigError, match=re.escape(message)):
        segment(cfg)
    assert not out.exists()


def test_a_segmenter_is_built_only_when_its_checkpoints_could_be_rebuilt(own_registry):
    own_registry.register_segmenter(Forgetful)
    with pytest.raises(ConfigError, match=r"does not record its keywords \['width'\] with self.save_hyperparameters"):
        registry.build_segmenter({"_target_": "test_segmenters.Forgetful", "width": 1})
    with pytest.raises(ConfigError, match=rf"model._target_={TARGET}: cannot be built .*colour"):
        registry.build_segmenter({"_target_": TARGET, "depth": 2, "colour": "red"})
    with pytest.raises(ConfigError, match="model: no _target_"):
        registry.build_segmenter({"depth": 2})


# --- the allow-list at load time ----------------------------------------------------------------------------


def test_checkpoint_round_trip_and_checkpoints_without_target(tmp_path):
    """A checkpoint's hyperparameters are the model's _target_ node; a checkpoint that names no class is refused."""
    model = tiny_model("model.normalize=zscore")
    path = save_checkpoint(tmp_path / "a.ckpt", dict(model.hparams), model.state_dict())
    loaded = registry.load_segmenter(path)
    assert type(loaded) is SegmenterModule and not loaded.training and loaded.input_normalization == "zscore"
    for name, tensor in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor), name
    nameless = save_checkpoint(
        tmp_path / "old.ckpt", {k: v for k, v in model.hparams.items() if k != "_target_"}, model.state_dict()
    )
    with pytest.raises(DataError, match="not a drgan segmenter checkpoint"):
        registry.load_segmenter(nameless)
    with pytest.raises(DataError, match="cannot be rebuilt from the saved keywords and weights"):
        registry.load_segmenter(save_checkpoint(tmp_path / "w.ckpt", {**model.hparams, "depth": 3}, model.state_dict()))


@pytest.mark.parametrize("target", ["payload_mod.Segmenter", "os.system", "drgan.models.gan_module.GANModule"])
def test_checkpoint_naming_a_class_outside_the_allow_list_is_refused_before_importing_it(target, tmp_path, monkeypatch):
    """The module a refused name points to is not imported: importing payload_mod would create the marker."""
    from drgan.analyze import AnalyzeSettings, analyze
    from drgan.evaluate import EvaluateSettings, evaluate

    marker = tmp_path / "payload_ran"
    (tmp_path / "payload_mod.py").write_text(
        f"import pathlib\npathlib.Path({str(marker)!r}).touch()\n\nclass Segmenter:\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    gan_loaded = "drgan.models.gan_module" in sys.modules
    path = save_checkpoint(tmp_path / "x.ckpt", {"_target_": target, "depth": 2})
    refused = rf"model={path}: _target_ '{target}' is not an allowed segmenter \(refused: nothing the file names"
    with pytest.raises(ConfigError, match=refused) as caught:
        registry.load_segmenter(path)
    assert TARGET in str(caught.value)  # the message lists what is allowed
    labels = disc_labels(32, seed=3)
    real = make_real(
        tmp_path / "real", {"x": disc_image(labels)}, {"x": (labels > 0) * 255}, {"train": [], "test": ["x"]}
    )
    with pytest.raises(ConfigError, match=refused):
        evaluate(EvaluateSettings.from_config(eval_cfg(real, tmp_path / "eval", [f"models=[{path}]"])))
    with pytest.raises(ConfigError, match=refused):
        analyze(
            AnalyzeSettings.from_config(
                compose([f"model={path}", f"images={real / 'images'}", f"out={tmp_path / 'an'}"], config_name="analyze")
            )
        )
    assert not marker.exists() and "payload_mod" not in sys.modules
    assert ("drgan.models.gan_module" in sys.modules) == gan_loaded
    assert not (tmp_path / "eval").exists() and not (tmp_path / "an").exists()


def test_registered_and_entry_point_segmenters_load(own_registry, tmp_path, monkeypatch):
    """A class joins the allow-list with @register_segmenter, or as an entry point of an installed package (only the
    entry point a checkpoint asks for is loaded)."""
    model = tiny_model()
    weights = model.state_dict()
    mine = {**model.hparams, "_target_": target_path(TinySegmenter)}
    with pytest.raises(ConfigError, match="test_segmenters.TinySegmenter' is not an allowed segmenter"):
        registry.load_segmenter(save_checkpoint(tmp_path / "mine.ckpt", mine, weights))
    own_registry.register_segmenter(TinySegmenter)
    assert type(registry.load_segmenter(tmp_path / "mine.ckpt")) is TinySegmenter

    (tmp_path / "plugin_seg.py").write_text(
        "from drgan.segmenters.module import SegmenterModule\n\nclass PluginSegmenter(SegmenterModule):\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    points = [
        EntryPoint("other", "never_imported_mod:Net", registry.ENTRY_POINT_GROUP),
        EntryPoint("plugin", "plugin_seg:PluginSegmenter", registry.ENTRY_POINT_GROUP),
    ]
    monkeypatch.setattr(registry, "entry_points", lambda group: [p for p in points if p.group == group])
    plugin = {**model.hparams, "_target_": "plugin_seg.PluginSegmenter"}
    loaded = registry.load_segmenter(save_checkpoint(tmp_path / "plugin.ckpt", plugin, weights))
    assert type(loaded).__name__ == "PluginSegmenter" and "never_imported_mod" not in sys.modules
    assert "plugin_seg.PluginSegmenter" in registry.registered_segmenters()


# --- a folder of predicted masks ----------------------------------------------------------------------------


def write_png(path: Path, values: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(values, np.uint8)).save(path)


def bar_dataset(tmp_path: Path) -> Path:
    """Test images a and b, 20 x 20 px above a 4-row info bar (rows 20-23), masks of the files' full size.
    a: true squares A (rows 2-5, cols 2-5) and B (rows 12-15, cols 12-15), 16 px each.
    b: true rectangles D (rows 4-9, cols 4-8) and E (rows 4-9, cols 10-14), 30 px each, column 9 between them."""
    truth = {k: np.zeros((24, 20), np.uint8) for k in "ab"}
    truth["a"][2:6, 2:6] = truth["a"][12:16, 12:16] = 255
    truth["b"][4:10, 4:9] = truth["b"][4:10, 10:15] = 255
    images = {k: np.where(m > 0, 0.8, 0.2) for k, m in truth.items()}
    for image in images.values():
        image[20:] = 0.0
    return make_real(tmp_path / "real", images, truth, {"train": [], "test": ["a", "b"]})


def test_evaluate_scores_a_folder_of_predicted_masks_like_a_checkpoint(tmp_path):
    """nnU-Net's output layout: <case>.png per test id, classes 0/1/2, its json files beside them.

    a.png (20 x 20, the cropped image's size): A exactly, plus a false square C (rows 2-3, cols 14-15), B missed:
    particle pixels P = 20, true T = 32, P & T = 16 -> DSC = 32 / 52; TP 1, FP 1, FN 1 -> AP50 = 1 / 3.
    b.png (20 x 24, the file's size: its bar rows go, as the image's do): D and E as particle, column 9 between them
    contour (class 2) -> DSC 1, AP50 1. Contour counted as particle would merge D and E into one 66-px instance
    (IoU 30 / 66 < 0.5 with each): AP50 0."""
    from drgan.evaluate import SCORES, EvaluateSettings, evaluate

    data = bar_dataset(tmp_path)
    preds = tmp_path / "nnunet_out"
    a = np.zeros((20, 20), np.uint8)
    a[2:6, 2:6] = a[2:4, 14:16] = 1
    b = np.zeros((24, 20), np.uint8)
    b[4:10, 4:9] = b[4:10, 10:15] = 1
    b[4:10, 9] = 2
    b[20:] = 1  # the info bar: dropped before scoring
    write_png(preds / "a.png", a)
    write_png(preds / "b.png", b)
    for name in ("dataset.json", "plans.json", "predict_from_raw_data_args.json"):
        (preds / name).write_text("{}")

    truth_a = np.zeros((20, 20), bool)
    truth_a[2:6, 2:6] = truth_a[12:16, 12:16] = True
    dsc_a = 2 * ((a == 1) & truth_a).sum() / ((a == 1).sum() + truth_a.sum())  # independent of drgan.metrics
    assert dsc_a == pytest.approx(32 / 52)

    model = tiny_model()
    ckpt = save_checkpoint(tmp_path / "net.ckpt", dict(model.hparams), model.state_dict())
    out = tmp_path / "eval"
    cfg = eval_cfg(data, out, ["crop_rows=[20,24]", f"models=[{preds},{ckpt}]", "inference.tile=32"])
    result = evaluate(EvaluateSettings.from_config(cfg))
    folder = result["runs"]["run0"]
    assert folder["dsc"] == pytest.approx((32 / 52 + 1) / 2) and folder["ap50"] == pytest.approx((1 / 3 + 1) / 2)
    rows = {(r["run"], r["image"]): r for r in result["rows"]}
    assert rows["run0", "b"]["ap50"] == pytest.approx(1.0) and rows["run0", "b"]["pq"] == pytest.approx(1.0)
    assert (rows["run0", "a"]["tp"], rows["run0", "a"]["fp"], rows["run0", "a"]["fn"]) == (1, 1, 1)
    assert set(result["runs"]["run1"]) == set(SCORES)  # the checkpoint run, in the same tables
    table = list(csv.DictReader((out / "results.csv").open()))
    assert [(r["run"], r["model"], r["image"]) for r in table] == [
        ("run0", str(preds), "a"),
        ("run0", str(preds), "b"),
        ("run0", str(preds), "mean"),
        ("run1", str(ckpt), "a"),
        ("run1", str(ckpt), "b"),
        ("run1", str(ckpt), "mean"),
    ]
    assert float(table[2]["dsc"]) == pytest.approx((32 / 52 + 1) / 2, abs=1e-6)
    md = (out / "results.md").read_text()
    assert f"run0: class maps read from {preds}; run1: tile 32" in md
    assert (out / "overlays" / "a.png").is_file()


def test_a_mask_folder_that_does_not_fit_the_test_images_is_refused_naming_every_file(tmp_path):
    from drgan.evaluate import EvaluateSettings, evaluate

    images = {k: np.full((16, 16), 0.5) for k in ("a", "b", "d", "e")}
    masks = {k: np.zeros((16, 16), np.uint8) for k in images}
    data = make_real(tmp_path / "real", images, masks, {"train": [], "test": sorted(images)})
    preds = tmp_path / "preds"
    write_png(preds / "a.png", np.zeros((17, 16)))  # one row too many
    bad = np.zeros((16, 16), np.uint8)
    bad[0, :3] = (1, 2, 255)  # 255: a binary 0/255 mask, not classes
    write_png(preds / "d.png", bad)
    write_png(preds / "e.png", np.zeros((16, 16)))
    write_png(preds / "e.tif", np.zeros((16, 16)))
    write_png(preds / "z.png", np.zeros((16, 16)))  # no test image z
    out = tmp_path / "eval"
    with pytest.raises(DataError) as caught:
        evaluate(EvaluateSettings.from_config(eval_cfg(data, out, [f"model={preds}"])))
    message = str(caught.value)
    assert message.startswith(f"model={preds}: the predicted masks do not match the 4 image(s)")
    for line in [
        "missing: no mask for 1 image(s): b",
        "extra: 1 mask(s) of no image to score: z.png",
        "a.png: size 16 x 17 px (W x H), its image a is 16 x 16 px",
        "d.png: values [255] (expected classes 0 background, 1 particle, 2 contour)",
        "e: several masks (e.png, e.tif)",
    ]:
        assert f"\n  {line}" in message, message
    assert not out.exists()  # refused before anything was computed or written

    empty = tmp_path / "run_folder"
    (empty / "checkpoints").mkdir(parents=True)
    with pytest.raises(DataError, match=r"a folder without predicted masks .*give model=.*last\.ckpt"):
        evaluate(EvaluateSettings.from_config(eval_cfg(data, out, [f"model={empty}"])))
    with pytest.raises(DataError, match=r"model=.*nowhere: no such file or folder \(expected a segmenter checkpoint"):
        evaluate(EvaluateSettings.from_config(eval_cfg(data, out, [f"model={tmp_path / 'nowhere'}"])))


def test_analyze_measures_a_folder_of_predicted_masks(tmp_path):
    from drgan.analyze import AnalyzeSettings, analyze

    labels = disc_labels(48, n=4, seed=2)
    images, preds = tmp_path / "images", tmp_path / "preds"
    write_png(images / "img.png", disc_image(labels) * 255)
    write_png(preds / "img.png", labels > 0)
    (preds / "dataset.json").write_text(json.dumps({"labels": {"background": 0, "particle": 1}}))
    cfg = compose(
        [f"model={preds}", f"images={images}", f"out={tmp_path / 'out'}", "min_area_px=0", "crop_rows=null"],
        config_name="analyze",
    )
    rows = analyze(AnalyzeSettings.from_config(cfg))
    from drgan.metrics.instance_scores import binarize_and_label

    expected = np.bincount(binarize_and_label((labels > 0).astype(np.int64)).ravel())[1:]
    assert sorted(r["area_px"] for r in rows) == sorted(expected.tolist())
    write_png(images / "second.png", disc_image(labels) * 255)
    with pytest.raises(DataError, match="missing: no mask for 1 image.*: second"):
        analyze(AnalyzeSettings.from_config(cfg))


# --- a toy segmenter, added as CONTRIBUTING.md says -------------------------------------------------------------

TOY_SEGMENTER = '''"""A segmenter outside drgan: one 3 x 3 convolution from the image to the three classes' logits."""

import lightning.pytorch as L
import torch
from torch.nn.functional import cross_entropy

from drgan.segmenters.module import particle_dsc
from drgan.segmenters.registry import register_segmenter


@register_segmenter
class PixelSegmenter(L.LightningModule):
    def __init__(self, width: int = 3, lr: float = 0.01):
        super().__init__()
        self.save_hyperparameters()  # plain keywords: the checkpoint is rebuilt from them
        self.net = torch.nn.Conv2d(1, 3, width, padding=width // 2)

    def forward(self, x):
        return self.net(x)  # (B, 1, H, W) -> (B, 3, H, W) logits: background, particle, contour

    def training_step(self, batch, batch_idx):
        loss = cross_entropy(self(batch[0]), batch[1], ignore_index=255)
        self.log("train/loss", loss, batch_size=len(batch[0]))
        return loss

    def validation_step(self, batch, batch_idx):
        logits = self(batch[0])
        self.log_dict(
            {"val/loss": cross_entropy(logits, batch[1], ignore_index=255), "val/dsc": particle_dsc(logits, batch[1])},
            batch_size=len(batch[0]),
        )

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=self.hparams.lr)
'''


def test_a_new_segmenter_is_a_registered_class_that_segment_trains_and_evaluate_loads(
    own_registry, tmp_path, monkeypatch
):
    """CONTRIBUTING.md, "a segmenter": a LightningModule decorated with @register_segmenter is the whole change.
    `segment` builds it from model._target_ and trains it (one step on a generated set), its checkpoint names the
    class, and `evaluate` rebuilds it through the allow-list and scores it; without the registration the same
    checkpoint is refused."""
    from omegaconf import OmegaConf, open_dict
    from test_segment import make_generated

    from drgan.evaluate import EvaluateSettings, evaluate
    from drgan.segment import segment

    (tmp_path / "toy_segmenter.py").write_text(TOY_SEGMENTER)
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        out = tmp_path / "run"
        cfg = compose(
            [
                f"data={make_generated(tmp_path / 'gen')}",
                f"out={out}",
                f"paths.root_dir={tmp_path}",
                "loader.crop=32",
                "loader.batch_size=4",
                "trainer.accelerator=cpu",
                "trainer.enable_progress_bar=false",
                "trainer.max_epochs=1",
            ],
            config_name="segment",
        )
        with open_dict(cfg):
            cfg.model = OmegaConf.create({"_target_": "toy_segmenter.PixelSegmenter", "width": 3})
        assert "train/loss" in segment(cfg)
        last = out / "checkpoints" / "last.ckpt"
        saved = torch.load(last, map_location="cpu", weights_only=True)["hyper_parameters"]
        assert saved == {"width": 3, "lr": 0.01, "_target_": "toy_segmenter.PixelSegmenter"}

        labels = disc_labels(40, seed=7)
        real = make_real(
            tmp_path / "real", {"x": disc_image(labels)}, {"x": (labels > 0) * 255}, {"train": [], "test": ["x"]}
        )
        result = evaluate(
            EvaluateSettings.from_config(eval_cfg(real, tmp_path / "eval", [f"models=[{last}]", "inference.tile=32"]))
        )
        assert set(result["runs"]) == {"run0"} and 0.0 <= result["runs"]["run0"]["dsc"] <= 1.0

        monkeypatch.setattr(registry, "_REGISTRY", {})  # the same checkpoint, the class not registered
        with pytest.raises(ConfigError, match="'toy_segmenter.PixelSegmenter' is not an allowed segmenter"):
            evaluate(
                EvaluateSettings.from_config(
                    eval_cfg(real, tmp_path / "eval2", [f"models=[{last}]", "inference.tile=32"])
                )
            )
    finally:
        sys.modules.pop("toy_segmenter", None)


# --- the learning-rate schedule -------------------------------------------------------------------------------


def test_poly_factor_falls_from_one_to_zero_as_computed_by_hand():
    from drgan.segmenters.module import poly_factor

    assert poly_factor(0, 10) == 1.0
    assert poly_factor(5, 10) == pytest.approx(0.5**0.9)  # 0.536
    assert poly_factor(9, 10) == pytest.approx(0.1**0.9)  # the last step's: 0.126
    assert poly_factor(10, 10) == 0.0 and poly_factor(12, 10) == 0.0  # never negative past the end


class RateLog(L.Callback):
    """The optimizer's learning rate at every training step."""

    def __init__(self):
        self.rates: list[float] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.rates.append(trainer.optimizers[0].param_groups[0]["lr"])


@pytest.mark.parametrize("schedule", ["constant", "poly"])
def test_the_rate_of_each_step_follows_the_schedule_over_max_epochs(schedule, tmp_path):
    """8 crops in batches of 2 for 2 epochs: 8 steps; poly's k-th step trains at lr (1 - k / 8)^0.9."""
    from drgan.segmenters.module import poly_factor

    torch.manual_seed(0)
    images = torch.rand(8, 1, 16, 16)
    masks = (images[:, 0] > 0.5).long()
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(images, masks), batch_size=2)
    model = tiny_model(f"model.lr_schedule={schedule}")
    log = RateLog()
    trainer = L.Trainer(max_epochs=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0, callbacks=[log], default_root_dir=tmp_path,
                        accelerator="cpu")  # fmt: skip
    trainer.fit(model, loader)
    lr = model.hparams.lr
    expected = [lr * (poly_factor(k, 8) if schedule == "poly" else 1.0) for k in range(8)]
    assert log.rates == pytest.approx(expected)


def test_a_resumed_poly_run_goes_on_at_the_rate_where_it_stopped(tmp_path):
    """A run resumed from its first epoch's checkpoint trains its second epoch at the rates the whole run did (steps
    4-7 of 8), not from the full rate again: the scheduler's step is in the checkpoint."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    torch.manual_seed(0)
    images = torch.rand(8, 1, 16, 16)
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(images, (images[:, 0] > 0.5).long()), 2)

    def fit(log, ckpt_path=None):
        saved = ModelCheckpoint(dirpath=tmp_path, save_top_k=-1, every_n_epochs=1, filename="{epoch}")
        trainer = L.Trainer(max_epochs=2, logger=False, enable_progress_bar=False, enable_model_summary=False,
                            limit_val_batches=0, callbacks=[log, saved], default_root_dir=tmp_path,
                            accelerator="cpu")  # fmt: skip
        trainer.fit(tiny_model("model.lr_schedule=poly"), loader, ckpt_path=ckpt_path)

    whole, resumed = RateLog(), RateLog()
    fit(whole)
    fit(resumed, ckpt_path=tmp_path / "epoch=0.ckpt")
    assert len(whole.rates) == 8 and resumed.rates == pytest.approx(whole.rates[4:])
    assert resumed.rates[0] < 0.6 * whole.rates[0]


def test_an_unknown_schedule_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match=r"model.lr_schedule='cosine': expected one of constant, poly"):
        tiny_model("model.lr_schedule=cosine")
