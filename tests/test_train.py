"""Training core: data module, discriminator, GANModule and `python -m drgan.train`.

Tiny everything: 24 px renders (the smallest a 3-layer PatchGAN takes), spp 1, 3 particles, synthetic
real images (bright discs on a dark background), 1-3 steps per run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import compose
from PIL import Image

from drgan.core.errors import ConfigError, DataError
from drgan.data.datamodule import RealPatchDataModule

MATERIALS = ["tio2_sem", "tio2_him", "sio2_him", "agnw_sem"]
SIZE = 24


def make_images(folder: Path, n: int = 3, size: int = 96, seed: int = 0) -> Path:
    """Bright discs (radius 4.5 px) on a dark noisy background, one corner left empty for background patches."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    for i in range(n):
        img = 0.15 + 0.02 * rng.standard_normal((size, size))
        for _ in range(14):
            cy, cx = rng.uniform(6, size - 6, 2)
            if cy > size - 30 and cx > size - 30:
                continue
            img[(yy - cy) ** 2 + (xx - cx) ** 2 <= 4.5**2] = 0.8
        Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)).save(folder / f"img{i}.png")
    return folder


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    return make_images(tmp_path_factory.mktemp("real") / "images")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# Fast stand-ins for the epoch-end callbacks: a random-projection "FID" on 4 images, few constellations.
CALLBACK_OVERRIDES = [
    "callbacks.fid.extractor={_target_:drgan.callbacks.RandomProjectionFeatures,dim:16}",
    "callbacks.fid.n_images=4",
    "+callbacks.fid.kid_subsets=5",
    "callbacks.best_epoch.n_phi=20",
    "callbacks.histograms.n_phi=20",
    "callbacks.sample_grid.n=2",
    "callbacks.progress_bar.refresh_rate=0",
    "~callbacks.grey_start",  # ~5 s of renders per run; tested on its own (test_grey_start_moves_the_renders_to_the_real_grey)
]


def tiny_overrides(
    data_dir: Path, out: Path, material: str = "tio2_sem", *, logger: str = "none", extra=()
) -> list[str]:
    return [
        f"material={material}",
        "material.n_particles=3",
        "material.meshes.count=3",
        f"renderer.resolution={SIZE}",
        "renderer.spp=1",
        "data.view_width=null",  # windows of the render size: the tiny discs at a 24 px scale, not a 256 px view
        f"data.dir={data_dir}",
        "data.crop_rows=null",
        "data.check_material=false",  # tiny discs of ~9 px against the material's 30 px: tests/test_polarity.py checks it
        "data.stride=8",
        "data.min_particles=1",
        "data.n_background=2",
        "data.segment.neck_depth=0.0",  # chosen by the sizes otherwise (a second scale search): tests/test_particles.py
        f"paths.output_dir={out}",
        f"paths.root_dir={out.parent}",
        f"logger={logger}",
        "trainer.accelerator=cpu",
        "trainer.enable_model_summary=false",
        *CALLBACK_OVERRIDES,
        *extra,
    ]


def run_train(overrides):
    from drgan.train import train

    return train(compose(overrides, config_name="train"))


# --- data module ------------------------------------------------------------------------------------------


def datamodule(data_dir, tmp_path, **kw):
    args = dict(
        dir=str(data_dir),
        split=None,
        patch_size=SIZE,
        stride=8,
        min_particles=1,
        n_background=2,
        cache_dir=str(tmp_path / "patches"),
        resolution=SIZE,
        # The lengths these tiny images were drawn for (discs of 9 px, partial ones not counted), set by hand.
        segment={"sigma": 1.0, "min_distance": 7, "min_area": 40, "max_area": 4000},
    )
    args.update(kw)
    return RealPatchDataModule(**args)


def test_datamodule_mines_caches_and_augments(images, tmp_path):
    dm = datamodule(images, tmp_path, batch_size=4)
    dm.setup("fit")
    assert dm.real_patches.shape[1:] == (SIZE, SIZE) and dm.real_patches.dtype == np.float32
    assert len(dm.real_patches) >= 4 and dm.background_patches.shape == (2, SIZE, SIZE)
    for name in ("patches.npz", "summary.json", "contact_sheet.png", "source.json"):
        assert (tmp_path / "patches" / name).is_file()
    batch = next(iter(dm.train_dataloader()))
    assert batch.shape == (4, 1, SIZE, SIZE) and batch.dtype == torch.float32
    assert 0.0 <= float(batch.min()) and float(batch.max()) <= 1.0
    # A second module with the same settings reads the cache (the resumed run's case).
    again = datamodule(images, tmp_path)
    again.setup("fit")
    np.testing.assert_array_equal(again.real_patches, dm.real_patches)


def test_an_epoch_is_steps_per_epoch_steps_whatever_the_number_of_patches(images, tmp_path):
    dm = datamodule(images, tmp_path, batch_size=2)
    dm.setup("fit")
    n = len(dm.real_patches)
    for steps in (3, n + 5, 3 * n):  # fewer steps than patches, and passes over them several times
        dm.steps_per_epoch = steps
        batches = list(dm.train_dataloader())
        assert len(batches) == steps and all(b.shape[0] == 2 for b in batches)
    # Every patch comes once per pass: 3 n steps of 2 patches are six permutations, each patch seen 6 times.
    torch.manual_seed(0)
    indices = list(dm.train_dataloader().sampler)
    assert np.bincount(indices, minlength=n).tolist() == [6] * n
    dm.steps_per_epoch = None  # one pass over the patches (the paper's epoch)
    assert len(list(dm.train_dataloader())) == n // 2
    with pytest.raises(ConfigError, match="steps_per_epoch"):
        datamodule(images, tmp_path, steps_per_epoch=0)


def test_the_grey_start_step_is_the_least_change_that_zeroes_the_differences():
    from drgan.callbacks.grey_start import gauss_newton_step

    jacobian = torch.tensor([[1.0, 0.0, 0.0, 1e-6], [0.0, 2.0, 1.0, 0.0]])  # 2 numbers, 4 biases
    residual = torch.tensor([0.3, -0.5])
    step = gauss_newton_step(jacobian, residual, max_step=10.0)
    np.testing.assert_allclose(jacobian @ step, -residual, atol=1e-3)  # zeroed to first order
    np.testing.assert_allclose(step, [-0.3, 0.2, 0.1, 0.0], atol=1e-3)  # the least-norm change: a bias that
    # hardly changes the numbers (the 4th) hardly moves, and the 2nd number's change is shared 2:1 by its biases
    assert gauss_newton_step(jacobian, residual, max_step=0.05).abs().max() == pytest.approx(0.05)  # the trust region
    assert gauss_newton_step(torch.zeros(2, 4), residual, 1.0) is None


def test_the_grey_anchor_is_zero_inside_the_real_range_and_pulls_back_from_outside():
    from drgan.callbacks.grey_start import GreyAnchor

    def segment(images):  # particles: the left half of each image
        masks = np.zeros(images.shape, bool)
        masks[:, :, :8] = True
        return masks

    def batch(particle, background):
        image = torch.full((1, 1, 16, 16), float(background))
        image[..., :8] = particle
        return image.requires_grad_(True)

    ranges = {"particle": [0.8, 1.2], "background": [0.9, 1.1]}
    bright = GreyAnchor(segment, "bright", {"particle": 0.6, "background": 0.2}, ranges, weight=10.0)
    assert float(bright(batch(0.6, 0.2))) == 0.0 and float(bright(batch(0.7, 0.21))) == 0.0  # inside: nothing
    images = batch(0.3, 0.2)  # particles at half the real grey: 0.3 below the range's 0.8
    penalty = bright(images)
    assert float(penalty) == pytest.approx(10.0 * 0.3**2)
    penalty.backward()
    assert float(images.grad[..., :8].sum()) < 0  # descending the penalty brightens the particles
    dark = GreyAnchor(segment, "dark", {"particle": 0.1, "background": 0.8}, ranges, weight=1.0)
    # dark particles: ratios of the negatives; a film at 0.9 is (1 - 0.9) / (1 - 0.8) = 0.5 x, 0.4 below 0.9
    assert float(dark(batch(0.1, 0.9))) == pytest.approx(0.4**2)


@pytest.mark.slow  # a tiny training's grey start: 12 steps of 4 renders with 3 adjoint passes each (~17 s on 2 cores)
def test_grey_start_moves_the_renders_to_the_real_grey(images, tmp_path):
    """The discs are grey 0.8 on a 0.15 film; the fresh FCN renders the middle of the limits. A few Adam steps on the
    output biases bring particle and background grey to the real patches' (their classical segmentation alike)."""
    out = tmp_path / "run"
    extra = ["trainer.max_epochs=1", "trainer.limit_train_batches=1", "+callbacks.grey_start._target_=drgan.callbacks.GreyStart",
             "+callbacks.grey_start.steps=12", "+callbacks.grey_start.spp=4", "+callbacks.grey_start.images=4"]  # fmt: skip
    run_train(tiny_overrides(images, out, extra=extra))
    record = json.loads((out / "grey_start.json").read_text())
    real, first = record["real"], record["first"]
    # each step measures a new sample of renders (3 particles of 24 px: the particle grey varies by ~0.1 between
    # samples), so the last steps' mean says where the biases have settled
    late = {k: np.mean([h[k] for h in record["history"][-5:]]) for k in ("particle", "background")}
    for key in ("particle", "background"):
        assert abs(late[key] - real[key]) < 0.5 * abs(first[key] - real[key]), (key, record)
    assert abs(late["particle"] - real["particle"]) < 0.12 and abs(late["background"] - real["background"]) < 0.03
    assert record["bias_after"] != record["bias_before"]


def test_real_patches_cover_the_view_at_any_render_resolution(images, tmp_path):
    """Rendering 24 px for a 48 px view: 48 px windows are mined and area-averaged to 24 px, so real and rendered
    patches show particles at one scale (mining 24 px windows would show them twice as large)."""
    from skimage.transform import resize

    from drgan.data.images import read_grey

    dm = datamodule(images, tmp_path, view_width=2 * SIZE, stride=16)
    dm.setup("fit")
    patches = dm.patches
    assert patches.train.shape[1:] == (SIZE, SIZE) and patches.background.shape[1:] == (SIZE, SIZE)
    assert patches.params["window"] == 2 * SIZE
    source = {p.stem: read_grey(p, None) for p in sorted(images.glob("*.png"))}
    for patch, name, (row, col) in zip(patches.train[:3], patches.train_ids, patches.train_positions):
        window = source[name][row : row + 2 * SIZE, col : col + 2 * SIZE]
        expected = resize(window, (SIZE, SIZE), order=1, anti_aliasing=True, preserve_range=True)
        np.testing.assert_allclose(patch, expected, atol=1e-6)
    # Without view_width (or equal to the patch size) nothing is resampled: the windows are the patches.
    plain = datamodule(images, tmp_path / "plain")
    plain.setup("fit")
    row, col = plain.patches.train_positions[0]
    window = source[plain.patches.train_ids[0]][row : row + SIZE, col : col + SIZE]
    np.testing.assert_array_equal(plain.patches.train[0], window)
    with pytest.raises(ConfigError, match="view_width=12.*less than data.patch_size=24"):
        datamodule(images, tmp_path, view_width=SIZE // 2)


def test_split_keeps_test_images_out(images, tmp_path):
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": ["img0", "img1"], "test": ["img2"]}))
    dm = datamodule(images, tmp_path, split=str(split))
    dm.setup("fit")
    assert set(dm.patches.train_ids) <= {"img0", "img1"} and dm.test_ids == ["img2"]
    assert "img2" not in dm.patches.background_ids


@pytest.mark.parametrize(
    "case, message",
    [
        ("empty", "holds no image files"),
        ("small", "smaller than a 24 x 24 patch"),
        ("missing_test_id", "no image for 1 requested id"),
        ("test_in_train", "appears in both"),
        ("size_mismatch", "data.patch_size=32 but renderer.resolution=24"),
    ],
)
def test_bad_inputs_fail_before_training(case, message, images, tmp_path):
    kw = {}
    folder = images
    if case == "empty":
        folder = tmp_path / "empty"
        folder.mkdir()
    elif case == "small":
        folder = tmp_path / "small"
        folder.mkdir()
        Image.fromarray(np.zeros((16, 40), np.uint8)).save(folder / "a.png")
    elif case in ("missing_test_id", "test_in_train"):
        test = ["nope"] if case == "missing_test_id" else ["img0"]
        (tmp_path / "split.json").write_text(json.dumps({"train": ["img0", "img1"], "test": test}))
        kw["split"] = str(tmp_path / "split.json")
    error = ConfigError if case == "size_mismatch" else DataError
    with pytest.raises(error, match=message):
        dm = datamodule(folder, tmp_path, patch_size=32 if case == "size_mismatch" else SIZE, **kw)
        dm.setup("fit")


def test_train_refuses_bad_data_before_building_the_model(tmp_path, monkeypatch):
    import drgan.models.gan_module as gm

    monkeypatch.setattr(
        gm.GANModule, "__init__", lambda *a, **k: pytest.fail("model built before the data were checked")
    )
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="holds no image files"):
        run_train(tiny_overrides(tmp_path / "empty", tmp_path / "run"))


# --- discriminator and module -----------------------------------------------------------------------------


def test_patchgan_shape_and_init():
    from drgan.models.discriminator import PatchDiscriminator

    d = PatchDiscriminator()
    convs = [m for m in d.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [64, 128, 256, 512, 1]
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in d.modules()) == 3
    assert d(torch.rand(2, 1, 256, 256)).shape == (2, 1, 30, 30)
    # Xavier uniform: |w| <= sqrt(6 / (fan_in + fan_out))
    w = convs[1].weight
    assert float(w.abs().max()) <= (6 / (64 * 16 + 128 * 16)) ** 0.5 + 1e-6
    with pytest.raises(ConfigError, match=">= 24 px"):
        d.check_size(16)


def test_compose_defaults_and_experiments():
    cfg = compose(config_name="train")
    assert cfg.material.name == "tio2_sem" and cfg.placement._target_ == "drgan.scene.placements.PoissonAgglomerates"
    assert cfg.model.loss == "lsgan" and cfg.model.lr_g == 2e-4 and cfg.model.lr_d == 1e-4
    assert list(cfg.model.betas) == [0.5, 0.999] and cfg.data.batch_size == 1 and cfg.trainer.max_epochs == 50
    assert cfg.data.patch_size == cfg.renderer.resolution == 256
    assert cfg.logger.mlflow.experiment_name == "tio2_sem"
    for material in MATERIALS:
        exp = compose([f"experiment={material}"], config_name="train")
        assert exp.material.name == material
    agnw = compose(["experiment=agnw_sem"], config_name="train")
    assert agnw.placement._target_ == "drgan.scene.placements.Random2D"
    fast = compose(["debug=fast"], config_name="train")
    assert fast.renderer.spp == 1 and "mlflow" not in (fast.logger or {})


@pytest.mark.parametrize("material", MATERIALS)
def test_every_material_trains_a_step(material, images, tmp_path):
    metrics = run_train(tiny_overrides(images, tmp_path / "run", material, extra=["trainer.fast_dev_run=1"]))
    assert np.isfinite(metrics["train/g_loss"]) and np.isfinite(metrics["train/d_loss"])
    assert metrics["train/skipped_steps"] == 0 and metrics["time/render_s"] > 0


@pytest.mark.slow  # two trainings and a resume: ~15 s
def test_resume_continues_epochs_and_mlflow_run(images, tmp_path, caplog):
    import logging

    import mlflow

    uri = f"sqlite:///{tmp_path}/mlruns/mlflow.db"
    out = tmp_path / "run"
    base = tiny_overrides(
        images,
        out,
        logger="mlflow",
        extra=[f"logger.mlflow.tracking_uri={uri}", "trainer.limit_train_batches=2", "trainer.log_every_n_steps=1"],
    )
    run_train(base + ["trainer.max_epochs=1"])
    first = json.loads((out / "metrics.json").read_text())
    assert first["global_step"] == 2 * 2  # two optimiser steps (D, G) per batch
    assert (out / "checkpoints" / "last.ckpt").is_file()
    run_id = (out / "mlflow_run_id.txt").read_text()

    caplog.clear()
    with caplog.at_level(logging.INFO, logger="drgan"):
        run_train(base + ["trainer.max_epochs=2", "ckpt_path=last"])
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "param" in r.getMessage()]
    second = json.loads((out / "metrics.json").read_text())
    assert second["epoch"] == 2 and second["global_step"] == 2 * first["global_step"]
    assert (out / "mlflow_run_id.txt").read_text() == run_id

    client = mlflow.MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("tio2_sem")
    runs = client.search_runs([experiment.experiment_id])
    assert [r.info.run_id for r in runs] == [run_id]
    run = runs[0]
    assert run.data.params["model/lr_g"] == "0.0002" and run.data.params["material/name"] == "tio2_sem"
    # the resume is recorded: the params keep the first start's values, the tags hold the resume's
    assert run.data.params["ckpt_path"] == "None" and run.data.params["trainer/max_epochs"] == "1"
    assert run.data.tags["resumed/ckpt_path"] == "last" and run.data.tags["resumed/trainer/max_epochs"] == "2"
    for key in (
        "train/g_loss",
        "train/d_loss",
        "train/d_real",
        "train/d_fake",
        "train/skipped_steps",
        "time/render_s",
        "time/step_s",
        "time/wall_s",
        "params/noise.sigma",
        "params/particle.roughness",
        "train/g_loss_epoch",
    ):
        assert key in run.data.metrics, key
    steps = [m.step for m in client.get_metric_history(run_id, "train/g_loss")]
    assert sorted(set(steps)) == [0, 1, 2, 3]  # logged per batch: the resumed epoch continues at batch 2

    from drgan.models.gan_module import GANModule

    module = GANModule.load_from_checkpoint(out / "checkpoints" / "last.ckpt", weights_only=True)
    assert module.phi_bank.shape[1:] == (3, 4)
    samples = module.parameter_samples(module.phi_bank[:2])
    assert samples.shape == (2, len(module.learned_keys)) and np.isfinite(samples).all()


@pytest.mark.slow  # two trainings: ~14 s
def test_init_from_starts_a_fresh_run_from_another_runs_weights(images, tmp_path):
    def weights(run):
        state = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["state_dict"]
        return {
            k: v
            for k, v in state.items()
            if k.startswith(("generator.regressor.", "discriminator."))
            and "running" not in k
            and "num_batches" not in k
        }

    one_step = ["trainer.limit_train_batches=1", "trainer.max_epochs=1"]
    run_train(tiny_overrides(images, tmp_path / "a", extra=one_step))
    source = tmp_path / "a" / "checkpoints" / "last.ckpt"
    # Learning rates of 1e-12 keep the copied weights (Adam moves each by ~lr); another seed initialises others.
    frozen = [*one_step, "seed=1", "model.lr_g=1e-12", "model.lr_d=1e-12"]
    run_train(tiny_overrides(images, tmp_path / "b", extra=[*frozen, f"init_from={source}"]))
    run_train(tiny_overrides(images, tmp_path / "c", extra=frozen))
    a, b, c = weights(tmp_path / "a"), weights(tmp_path / "b"), weights(tmp_path / "c")
    assert all(torch.allclose(a[k], b[k], rtol=0, atol=1e-9) for k in a)
    assert not any(torch.allclose(a[k], c[k], rtol=0, atol=1e-3) for k in a if "weight.original1" in k)
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["epoch"] == 1  # its own count, not a resume

    with pytest.raises(ConfigError, match=r"init_from=.*input is 4 x material.n_particles"):
        run_train(
            tiny_overrides(images, tmp_path / "d", extra=[*one_step, f"init_from={source}", "material.n_particles=4"])
        )
    with pytest.raises(ConfigError, match="init_from=.*no such checkpoint file"):
        run_train(tiny_overrides(images, tmp_path / "e", extra=[f"init_from={tmp_path / 'missing.ckpt'}"]))
    assert not (tmp_path / "e" / "patches").exists()  # refused before any patch was mined


def test_background_texture_reaches_training_and_needs_background_patches(images, tmp_path, monkeypatch):
    from drgan.models.generator import Generator

    seen = []
    original = Generator.set_background
    monkeypatch.setattr(
        Generator, "set_background", lambda self, texture: (seen.append(texture), original(self, texture))[1]
    )
    texture = ["material.background_texture.enabled=true", "material.background_texture.highpass_px=2"]
    metrics = run_train(tiny_overrides(images, tmp_path / "run", extra=[*texture, "trainer.fast_dev_run=1"]))
    assert np.isfinite(metrics["train/g_loss"]) and len(seen) == 1 and len(seen[0]) == 2  # data.n_background=2
    with pytest.raises(
        ConfigError, match="background_texture.enabled: no real background patches.*data.n_background > 0"
    ):
        run_train(
            tiny_overrides(images, tmp_path / "none", extra=[*texture, "data.n_background=0", "trainer.fast_dev_run=1"])
        )
    assert not (tmp_path / "none" / "patches").exists()  # refused before any patch was mined


def test_lr_decay_factor_and_bad_settings():
    from drgan.models.gan_module import LRDecay

    decay = LRDecay(start_step=10, steps=4, final_factor=0.2)
    assert [decay(s) for s in (0, 10, 11, 12, 14, 100)] == pytest.approx([1.0, 1.0, 0.8, 0.6, 0.2, 0.2])
    assert LRDecay.from_config(None) is None and LRDecay.from_config({"start_step": None, "steps": 3}) is None
    for bad in (
        {"start_step": -1, "steps": 3},
        {"start_step": 0, "steps": 0},
        {"start_step": 0, "steps": 3, "final_factor": 1.5},
    ):
        with pytest.raises(ConfigError, match="model.lr_decay"):
            LRDecay.from_config(bad)


def test_optimisers_are_named_by_the_config_and_checked_before_training(tmp_path):
    """model.optimizer_g/_d: `_target_` + `_partial_`, built when training starts; any torch.optim class, no other
    code; bad keywords fail when the module is built."""
    from drgan.models.gan_module import GANModule

    base = tiny_overrides(tmp_path / "none", tmp_path / "run")
    module = GANModule.from_config(compose([*base, "model.lr_g=3e-5"], config_name="train"), m=2)
    opt_g, opt_d = module.configure_optimizers()
    assert type(opt_g) is torch.optim.Adam and opt_g.param_groups[0]["lr"] == 3e-5
    assert opt_g.param_groups[0]["betas"] == (0.5, 0.999) and opt_d.param_groups[0]["lr"] == 1e-4
    assert {id(p) for p in opt_g.param_groups[0]["params"]} == {id(p) for p in module.generator.parameters()}
    swapped = [
        *base,
        "model.optimizer_d._target_=torch.optim.SGD",
        "~model.optimizer_d.betas",
        "+model.optimizer_d.momentum=0.9",
    ]
    opt_d = GANModule.from_config(compose(swapped, config_name="train"), m=2).configure_optimizers()[1]
    assert type(opt_d) is torch.optim.SGD and opt_d.param_groups[0]["momentum"] == 0.9

    for bad, message in (
        (["model.optimizer_g._target_=os.system"], "expected a torch.optim optimiser class"),
        (["model.optimizer_g._target_=torch.optim.SGD"], "unexpected keyword argument 'betas'"),
        (["model.lr_d=-1"], "model.optimizer_d: .*Invalid learning rate"),
        (["model.optimizer_g._partial_=false"], "expected _partial_: true"),
    ):
        with pytest.raises(ConfigError, match=message):
            GANModule.from_config(compose([*base, *bad], config_name="train"), m=2)


def test_module_takes_built_parts_and_rebuilds_from_its_saved_config(tmp_path):
    from drgan.models import build
    from drgan.models.gan_module import GANModule, GANTraining

    cfg = compose(tiny_overrides(tmp_path / "none", tmp_path / "run"), config_name="train")
    with pytest.raises(TypeError, match="from_config"):
        GANModule(cfg)  # the config goes through from_config, not the constructor
    built = GANModule.from_config(cfg, m=4)
    # The same parts built by hand (generator first: both draw their weights from torch's seeded RNG).
    by_hand = GANModule(
        build.build_generator(cfg, seed=0),
        build.build_discriminator(cfg.model),
        build.layout_sampler(cfg),
        GANTraining.from_config(cfg.model),
        m=4,
    )
    assert built.state_dict().keys() == by_hand.state_dict().keys()
    for key, value in built.state_dict().items():
        assert torch.equal(value, by_hand.state_dict()[key]), key
    assert (built.lr_g, built.lr_d, built.loss_kind) == (cfg.model.lr_g, cfg.model.lr_d, cfg.model.loss)
    with pytest.raises(ConfigError, match="model.loss"):
        GANTraining.from_config({"loss": "wasserstein"})

    # A checkpoint rebuilds the module from the config saved in it; one built by hand has none to rebuild from.
    for module, name in ((built, "built.ckpt"), (by_hand, "by_hand.ckpt")):
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, tmp_path / name)
    loaded = GANModule.load_from_checkpoint(tmp_path / "built.ckpt")
    assert torch.equal(loaded.phi_bank, built.phi_bank) and len(loaded.phi_bank) == 4
    assert loaded.generator.scene.spec == built.generator.scene.spec
    with pytest.raises(ConfigError, match="no model config"):
        GANModule.load_from_checkpoint(tmp_path / "by_hand.ckpt")


def test_lr_decay_follows_steps_across_resume(images, tmp_path):
    out = tmp_path / "run"
    decay = [
        "model.lr_decay.start_step=1",
        "model.lr_decay.steps=2",
        "model.lr_decay.final_factor=0.25",
        "trainer.limit_train_batches=2",
    ]
    base = tiny_overrides(images, out, extra=decay)

    def lrs():
        state = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
        return [opt["param_groups"][0]["lr"] for opt in state["optimizer_states"]]

    run_train(base + ["trainer.max_epochs=1"])
    assert lrs() == pytest.approx([2e-4 * 0.625, 1e-4 * 0.625])  # 2 steps: 1 at full rate, then half-way down
    run_train(base + ["trainer.max_epochs=2", "ckpt_path=last"])
    assert lrs() == pytest.approx([2e-4 * 0.25, 1e-4 * 0.25])  # the schedule resumed at step 2, not 0


def test_non_finite_steps_are_skipped_then_stop_training(images, tmp_path, monkeypatch):
    from drgan.models.discriminator import PatchDiscriminator

    forward = PatchDiscriminator.forward
    calls = {"n": 0}

    def nan_for_first_two_steps(self, image):
        calls["n"] += 1
        out = forward(self, image)
        # D is called 3 times per step (real, detached fake, fake for G): poison steps 1 and 2.
        return out * float("nan") if calls["n"] <= 2 * 2 else out

    monkeypatch.setattr(PatchDiscriminator, "forward", nan_for_first_two_steps)
    out = tmp_path / "run"
    base = tiny_overrides(images, out, extra=["model.max_consecutive_nonfinite=3", "trainer.max_epochs=1"])
    metrics = run_train(base + ["trainer.limit_train_batches=3"])
    assert metrics["train/skipped_steps_total"] == 2 and np.isfinite(metrics["train/g_loss"])

    monkeypatch.setattr(PatchDiscriminator, "forward", lambda self, image: forward(self, image) * float("nan"))
    with pytest.raises(RuntimeError, match="3 steps in a row had a non-finite loss or gradient.*lower learning rates"):
        run_train(base + ["trainer.limit_train_batches=5"])


@pytest.mark.slow  # two processes' start-up: ~25 s
def test_ddp_on_two_cpu_processes_scores_the_same_fid_images(images, tmp_path):
    """trainer=ddp_cpu with 2 processes trains, and its FID (each rank renders a share, features gathered)
    equals the FID of the same images rendered in one process from the saved weights."""
    from drgan.callbacks.fid import FID_SEED_BASE, RandomProjectionFeatures, render_samples
    from drgan.data.patches import PatchSet
    from drgan.metrics.feature_distances import FeatureStats
    from drgan.models.gan_module import GANModule

    out = tmp_path / "run"
    overrides = tiny_overrides(
        images,
        out,
        extra=["trainer=ddp_cpu", "trainer.limit_train_batches=2", "trainer.max_epochs=1", "callbacks.fid.n_images=5"],
    )  # 5: 3 renders per rank, one dropped
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "-m", "drgan.train", *overrides],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    fid_ddp = json.loads((out / "checkpoints" / "best_epoch.json").read_text())["history"][0]["fid"]
    assert json.loads((out / "metrics.json").read_text())["val/fid"] == pytest.approx(fid_ddp)

    module = GANModule.load_from_checkpoint(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    module.eval()
    extractor = RandomProjectionFeatures(dim=16)
    real = FeatureStats.from_features(extractor.features(PatchSet.load(out / "patches").train))
    fake = render_samples(module, 5, FID_SEED_BASE)  # epoch 0's FID seeds
    assert FeatureStats.from_features(extractor.features(fake)).fid(real) == pytest.approx(fid_ddp, rel=1e-6)


# joblib: parallel processes on this machine; submitit_local: submitit's job machinery (pickled jobs, one
# folder per job, results collected), as on SLURM, but run as local processes.
LAUNCHERS = {
    "joblib": ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
    "submitit_local": ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10"],
}


@pytest.mark.slow  # a process per job: ~40 s each
@pytest.mark.parametrize("launcher", sorted(LAUNCHERS))
def test_sweep_makes_two_mlflow_runs(launcher, images, tmp_path):
    import mlflow

    if launcher == "submitit_local":
        pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="extra `cluster` (hydra-submitit-launcher)")
    uri = f"sqlite:///{tmp_path}/mlruns/mlflow.db"
    overrides = [
        o for o in tiny_overrides(images, tmp_path / "unused", logger="mlflow") if not o.startswith("paths.output_dir")
    ]
    cmd = [
        sys.executable, "-m", "drgan.train", "-m", *LAUNCHERS[launcher],
        "model.lr_g=1e-4,2e-4", "trainer.limit_train_batches=1", "trainer.log_every_n_steps=1", "trainer.max_epochs=1", "run_name=sweep",
        f"logger.mlflow.tracking_uri={uri}", f"paths.root_dir={tmp_path}", *overrides,
    ]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    client = mlflow.MlflowClient(tracking_uri=uri)
    runs = client.search_runs([client.get_experiment_by_name("tio2_sem").experiment_id])
    assert sorted(r.data.params["model/lr_g"] for r in runs) == ["0.0001", "0.0002"]
    assert all({"train/g_loss", "train/d_loss", "train/g_loss_epoch"} <= set(r.data.metrics) for r in runs)
    assert sorted(
        p.name for p in (tmp_path / "multirun" / "tio2_sem" / "sweep").iterdir() if p.is_dir() and p.name[0] != "."
    ) == ["0", "1"]


def test_a_step_whose_generator_gradient_is_not_finite_changes_no_weights(images, tmp_path, monkeypatch):
    """Finite losses, but the renderer's gradient is NaN: G's half fails after D's half succeeded, and D's update
    (weights, batch-norm statistics, Adam state) must be undone."""
    from drgan.models.gan_module import GANModule
    from drgan.scene import scene

    backward = scene._RenderFunction.backward

    def nan_gradient(ctx, grad_image):
        grads, *rest = backward(ctx, grad_image)
        return (grads * float("nan"), *rest)

    monkeypatch.setattr(scene._RenderFunction, "backward", staticmethod(nan_gradient))
    seen = []
    step = GANModule.training_step

    def recording_step(self, batch, batch_idx):
        before = {k: v.clone() for k, v in self.discriminator.state_dict().items()}
        opt_d = self.optimizers()[1].optimizer
        step(self, batch, batch_idx)
        seen.append((before, {k: v.clone() for k, v in self.discriminator.state_dict().items()}, len(opt_d.state)))

    monkeypatch.setattr(GANModule, "training_step", recording_step)
    metrics = run_train(
        tiny_overrides(images, tmp_path / "run", extra=["trainer.max_epochs=1", "trainer.limit_train_batches=2"])
    )
    assert metrics["train/skipped_steps_total"] == 2 and len(seen) == 2
    for before, after, adam_entries in seen:
        assert all(torch.equal(before[k], after[k]) for k in before), "D changed in a skipped step"
        assert adam_entries == 0  # no Adam moment was ever stored: D's optimiser state rolled back too


def test_the_generator_step_computes_no_gradient_for_the_discriminators_weights(images, tmp_path, monkeypatch):
    """Per step D's weight gradients are computed once (its own step); G's loss passes through D for D's input
    gradient only (Lightning's optimizer toggle around the forward), and G still learns."""
    from drgan.models.gan_module import GANModule

    seen = []
    step = GANModule.training_step

    def counting_step(self, batch, batch_idx):
        counts = {"d_weight": 0}
        weights = [p for p in self.discriminator.parameters() if p.dim() == 4]  # conv kernels

        def count(grad):
            counts["d_weight"] += 1
            return grad

        hooks = [w.register_hook(count) for w in weights]
        g_before = [p.detach().clone() for p in self.generator.parameters()]
        try:
            step(self, batch, batch_idx)
        finally:
            for hook in hooks:
                hook.remove()
        g_moved = any(not torch.equal(a, b) for a, b in zip(g_before, self.generator.parameters()))
        seen.append((counts["d_weight"], len(weights), g_moved))

    monkeypatch.setattr(GANModule, "training_step", counting_step)
    metrics = run_train(
        tiny_overrides(images, tmp_path / "run", extra=["trainer.max_epochs=1", "trainer.limit_train_batches=2"])
    )
    assert metrics["train/skipped_steps_total"] == 0 and len(seen) == 2
    for computed, n_weights, g_moved in seen:
        assert computed == n_weights  # once each (the D step), not twice (D step + G step)
        assert g_moved
