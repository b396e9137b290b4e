"""Checkpoint loading that cannot run code (drgan.core.checkpoint_io) at every entry point that reads a checkpoint.

A crafted checkpoint holds an object whose unpickling would create a marker file (pathlib.Path.touch). Each
entry point must refuse it with a message naming the setting and the file, and the marker must not exist
afterwards: nothing in the file ran. Real tiny checkpoints (a 1-step GAN run shared with test_generate, a
1-epoch segmenter) still load at each site, and with the bare ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import pathlib
import shutil
from pathlib import Path

import pytest
import torch
from conftest import compose
from test_generate import tiny_run  # noqa: F401  (session fixture: the 1-step GAN run folder)
from test_segment import disc_image, disc_labels, eval_cfg, make_generated, make_real, tiny_segment_overrides
from test_train import make_images, run_train, tiny_overrides

from drgan import generate as gen
from drgan.core.checkpoint_io import load_checkpoint
from drgan.core.errors import ConfigError, DataError
from drgan.synthetic.source import checkpoint_config, load_module

pytestmark = pytest.mark.usefixtures("one_torch_thread")

REFUSED = "refused: the file holds Python objects that could run code when loaded"


class TouchOnLoad:
    """Unpickling this calls pathlib.Path.touch(marker): code that a checkpoint file brings along."""

    def __init__(self, marker: Path):
        self.marker = Path(marker)

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


@pytest.fixture
def crafted(tmp_path) -> tuple[Path, Path]:
    """(a .ckpt shaped like a drgan checkpoint, plus the payload; the marker file its payload would create)."""
    marker = tmp_path / "payload_ran"
    path = tmp_path / "crafted.ckpt"
    torch.save(
        {
            "state_dict": {},
            "hyper_parameters": {"cfg": {"material": {}}, "kind": "drgan_segmenter"},
            "payload": TouchOnLoad(marker),
        },
        path,
    )
    return path, marker


def test_the_payload_would_run(crafted, tmp_path):
    """Control: calling what the payload's reduce names (what an unrestricted unpickler does) creates the marker,
    so the marker's absence in the tests below means that nothing ran."""
    path, marker = crafted
    function, args = TouchOnLoad(tmp_path / "control").__reduce__()
    function(*args)
    assert (tmp_path / "control").is_file()
    with pytest.raises(ConfigError, match=rf"ckpt=.*crafted.ckpt: {REFUSED} \(Unsupported global"):
        load_checkpoint(path, "ckpt")
    assert not marker.exists()


# --- refused at every entry point ---------------------------------------------------------------------------


def test_generate_refuses_a_crafted_checkpoint(crafted, tiny_run):  # noqa: F811
    path, marker = crafted
    with pytest.raises(ConfigError, match=f"ckpt=.*{REFUSED}"):
        checkpoint_config(path)
    saved = checkpoint_config(tiny_run / "checkpoints" / "best.ckpt")
    with pytest.raises(ConfigError, match=f"ckpt=.*{REFUSED}"):
        load_module(path, saved)
    out = path.parent / "out"
    with pytest.raises(ConfigError, match=f"ckpt=.*{REFUSED}"):
        gen.generate(
            compose([f"ckpt={path}", f"out={out}", "n=1", "n_background=0", "progress=false"], config_name="generate")
        )
    assert not marker.exists() and not out.exists()


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    return make_images(tmp_path_factory.mktemp("real") / "images")


def test_train_refuses_crafted_init_from_and_ckpt_path_before_mining(crafted, images, tmp_path):
    path, marker = crafted
    out = tmp_path / "run"
    with pytest.raises(ConfigError, match=f"init_from=.*{REFUSED}"):
        run_train(tiny_overrides(images, out, extra=[f"init_from={path}"]))
    with pytest.raises(ConfigError, match=f"ckpt_path=.*{REFUSED}"):
        run_train(tiny_overrides(images, out, extra=[f"ckpt_path={path}"]))
    (out / "checkpoints").mkdir(parents=True)
    shutil.copy(path, out / "checkpoints" / "last.ckpt")  # a crafted file put in the run folder
    with pytest.raises(ConfigError, match=f"ckpt_path=.*last.ckpt: {REFUSED}"):
        run_train(tiny_overrides(images, out, extra=["ckpt_path=last"]))
    assert not marker.exists()
    assert not (out / "patches").exists()  # refused before any patch was mined


def test_segment_evaluate_and_analyze_refuse_a_crafted_checkpoint(crafted, tmp_path):
    from drgan.analyze import AnalyzeSettings, analyze
    from drgan.evaluate import EvaluateSettings, evaluate
    from drgan.segment import segment
    from drgan.segmenters.module import load_segmenter

    path, marker = crafted
    with pytest.raises(DataError, match=f"model=.*{REFUSED}"):
        load_segmenter(path)
    labels = disc_labels(32, seed=3)
    real = make_real(
        tmp_path / "real", {"x": disc_image(labels)}, {"x": (labels > 0) * 255}, {"train": [], "test": ["x"]}
    )
    with pytest.raises(DataError, match=f"model=.*{REFUSED}"):
        evaluate(EvaluateSettings.from_config(eval_cfg(real, tmp_path / "eval", [f"models=[{path}]"])))
    with pytest.raises(DataError, match=f"model=.*{REFUSED}"):
        analyze(
            AnalyzeSettings.from_config(
                compose([f"model={path}", f"images={real / 'images'}", f"out={tmp_path / 'an'}"], config_name="analyze")
            )
        )
    data = make_generated(tmp_path / "gen", n=4)
    with pytest.raises(ConfigError, match=f"ckpt_path=.*{REFUSED}"):
        segment(
            compose(
                [f"data={data}", f"out={tmp_path / 'seg'}", f"ckpt_path={path}", "logger=none"],
                config_name="segment",
            )
        )
    assert not marker.exists()


# --- damaged and foreign files ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "content, message",
    [
        (b"hello", "not a readable PyTorch checkpoint"),
        (b"", "not a readable PyTorch checkpoint"),
        ("truncated", "not a readable PyTorch checkpoint"),
        ("tensor", "a PyTorch file but not a Lightning checkpoint"),
    ],
)
def test_damaged_or_foreign_files_get_a_clear_message(content, message, tiny_run, tmp_path):  # noqa: F811
    path = tmp_path / "x.ckpt"
    if content == "truncated":
        whole = (tiny_run / "checkpoints" / "best.ckpt").read_bytes()
        path.write_bytes(whole[: len(whole) // 2])
    elif content == "tensor":
        torch.save(torch.zeros(3), path)
    else:
        path.write_bytes(content)
    with pytest.raises(ConfigError, match=f"init_from={path}: {message}"):
        load_checkpoint(path, "init_from")
    with pytest.raises(ConfigError, match="init_from=.*nope.ckpt: no such checkpoint file"):
        load_checkpoint(tmp_path / "nope.ckpt", "init_from")


# --- real checkpoints still load ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def segmenter_run(tmp_path_factory) -> Path:
    from drgan.segment import segment

    root = tmp_path_factory.mktemp("seg")
    data = make_generated(root / "gen", n=4)
    out = root / "run"
    segment(compose(tiny_segment_overrides(data, root, out, "logger=none", "trainer.max_epochs=1"), "segment"))
    return out


def test_real_checkpoints_need_no_allow_listed_class(tiny_run, segmenter_run):  # noqa: F811
    """Every kind of checkpoint drgan writes loads with torch's default weights-only list: content that needs a
    class (an OmegaConf node, a numpy RNG state, a scheduler's lambda object) would fail here first."""
    files = sorted((tiny_run / "checkpoints").rglob("*.ckpt")) + sorted((segmenter_run / "checkpoints").rglob("*.ckpt"))
    names = {f.relative_to(f.parents[1] if f.parent.name == "epochs" else f.parent).as_posix() for f in files}
    assert {"best.ckpt", "last.ckpt", "epochs/epoch_000.ckpt"} <= names
    for f in files:
        checkpoint = torch.load(f, map_location="cpu", weights_only=True)
        assert "state_dict" in checkpoint, f


def test_real_checkpoints_load_at_every_site(tiny_run, segmenter_run, tmp_path):  # noqa: F811
    from drgan.launch.runtime import resolve_checkpoint
    from drgan.segmenters.module import load_segmenter

    best, last = tiny_run / "checkpoints" / "best.ckpt", tiny_run / "checkpoints" / "last.ckpt"
    saved = checkpoint_config(best)
    assert saved["material"]["n_particles"] == 3
    module = load_module(best, saved)
    assert not module.training and module.phi_bank.shape[1:] == (3, 4)
    assert module.load_weights(last) > 0  # init_from's reader
    assert resolve_checkpoint(str(last), tmp_path) == str(last)  # train / segment resume: checked, then Lightning
    assert resolve_checkpoint("last", tiny_run) == str(last)
    segmenter = load_segmenter(segmenter_run / "checkpoints" / "last.ckpt")
    assert not segmenter.training


def test_a_checkpoint_naming_the_former_layout_classes_still_loads(tiny_run, tmp_path):  # noqa: F811
    """Checkpoints saved while the size distributions and placements were classes of drgan.scene.layout name them
    there (size._target_, placement._target_ of the saved config): they load, with the same classes and the same
    constellations, as the same checkpoint naming drgan.scene.sizes and drgan.scene.placements."""
    best = tiny_run / "checkpoints" / "best.ckpt"
    checkpoint = torch.load(best, map_location="cpu", weights_only=True)
    cfg = checkpoint["hyper_parameters"]["cfg"]
    assert cfg["size"]["_target_"].startswith("drgan.scene.sizes.")
    assert cfg["placement"]["_target_"].startswith("drgan.scene.placements.")
    for group in ("size", "placement"):
        cfg[group]["_target_"] = "drgan.scene.layout." + cfg[group]["_target_"].rsplit(".", 1)[1]
    old = tmp_path / "old.ckpt"
    torch.save(checkpoint, old)
    saved = checkpoint_config(old)
    assert saved["placement"]["_target_"] == "drgan.scene.layout.PoissonAgglomerates"
    then, now = load_module(old, saved), load_module(best, checkpoint_config(best))
    assert then.layouts == now.layouts
    assert torch.equal(then.phi_bank, now.phi_bank) and (then.layouts(4, seed=1) == now.layouts(4, seed=1)).all()
