"""Callbacks: best-epoch selection, parameter spread, and a tiny 2-epoch training with FID (random-projection
features instead of Inception, for speed), best.ckpt/best_epoch.json, MLflow metrics and plots, and resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_train import images, make_images, run_train, tiny_overrides  # noqa: F401  (fixtures)

from drgan.callbacks import RandomProjectionFeatures, parameter_spread, select_best
from drgan.callbacks.best_epoch import within_brightness
from drgan.core.errors import ConfigError


def test_select_best_prefers_broadest_of_top_k():
    fids = [50, 40, 45, 41, 60, 42, 39]
    spreads = [0.9, 0.05, 0.30, 0.10, 0.95, 0.20, 0.01]
    history = [{"epoch": e, "fid": f, "spread": s} for e, (f, s) in enumerate(zip(fids, spreads))]
    best, table = select_best(history, top_k=5, fid_margin=None)
    # Five lowest FIDs: epochs 6 (39), 1 (40), 3 (41), 5 (42), 2 (45); epoch 2 is broadest among them.
    assert [h["epoch"] for h in table] == [6, 1, 3, 5, 2]
    assert best["epoch"] == 2
    # With the default 10 % margin only FIDs up to 42.9 compete: epoch 2 (45) is out, epoch 5 (42) the broadest left.
    assert select_best(history, top_k=5)[0]["epoch"] == 5
    # Epochs 0 and 4 are broader but not among the top 5 FIDs; top_k=1 is the plain lowest FID.
    assert select_best(history, top_k=1)[0]["epoch"] == 6
    assert (
        select_best(history + [{"epoch": 7, "fid": float("nan"), "spread": 1.0}], 5, fid_margin=None)[0]["epoch"] == 2
    )
    assert select_best([], 5) == (None, [])


def test_in_a_short_run_the_fid_still_weighs():
    """Three epochs are all among the "5 lowest": without the margin, the broadest wins whatever its FID."""
    history = [
        {"epoch": 0, "fid": 300.0, "spread": 0.40},
        {"epoch": 1, "fid": 150.0, "spread": 0.30},
        {"epoch": 2, "fid": 100.0, "spread": 0.10},
    ]
    assert select_best(history, top_k=5, fid_margin=None)[0]["epoch"] == 0
    assert select_best(history, top_k=5)[0]["epoch"] == 2
    assert select_best(history, top_k=5, fid_margin=0.5)[0]["epoch"] == 1  # 150 <= 1.5 x 100


def test_an_epoch_with_inverted_contrast_never_wins_even_at_the_right_mean_grey():
    """Dark real particles (0.3) on a bright stage (0.75). Epoch 0's particles are brighter than its stage:
    whole-image brightness 1.0 x real, lowest FID; particles and stage each within 0.5-2x."""
    from drgan.callbacks.fid import contrast, level_ratio

    def entry(epoch, fid, spread, particle, background):
        return {
            "epoch": epoch,
            "fid": fid,
            "spread": spread,
            "brightness": 1.0,
            "contrast": contrast(particle, background, "dark"),
            "particle_brightness": level_ratio(particle, 0.3, "dark"),
            "background_brightness": level_ratio(background, 0.75, "dark"),
        }

    inverted, right = entry(0, 80.0, 0.3, 0.55, 0.50), entry(1, 85.0, 0.2, 0.35, 0.70)
    assert 0.5 <= inverted["particle_brightness"] <= 2.0 and 0.5 <= inverted["background_brightness"] <= 2.0
    assert inverted["contrast"] < 1 < right["contrast"]
    assert select_best([inverted, right], 5, brightness_range=None)[0]["epoch"] == 0
    assert select_best([inverted, right], 5, brightness_range=(0.5, 2.0))[0]["epoch"] == 1
    # a washed-out film (0.95 against 0.75: its negative 0.2 x the real one's) is out, even at a fine mean grey
    washed = entry(2, 70.0, 0.3, 0.35, 0.95)
    assert select_best([washed, right], 5, brightness_range=(0.5, 2.0))[0]["epoch"] == 1


def test_fid_levels_and_contrast_by_hand():
    from drgan.callbacks.fid import contrast, level_sums, levels

    images = np.array([[[0.2, 0.8], [0.2, 0.2]], [[0.4, 0.4], [0.9, 0.7]]])
    masks = np.array([[[False, True], [False, False]], [[False, False], [True, True]]])
    particle, background = levels(level_sums(images, masks))
    assert particle == pytest.approx((0.8 + 0.9 + 0.7) / 3) and background == pytest.approx((0.2 * 3 + 0.8) / 5)
    assert contrast(particle, background, "bright") == pytest.approx(particle / background)
    assert contrast(0.3, 0.75, "dark") == pytest.approx(2.5) and contrast(0.6, 0.5, "dark") < 1
    from drgan.callbacks.fid import level_ratio  # dark particles: ratios of the negatives, stable near black

    assert level_ratio(0.08, 0.03, "bright") == pytest.approx(0.08 / 0.03)
    assert level_ratio(0.08, 0.03, "dark") == pytest.approx(0.92 / 0.97)
    assert level_ratio(0.95, 0.75, "dark") == pytest.approx(0.2)  # a washed-out film is far off


@pytest.mark.parametrize("polarity", ["bright", "dark"])
def test_particle_levels_are_measured_alike_on_real_and_synthetic_images(polarity):
    """Particles with a bright core and a shaded rim at the background's grey (as TiO2 SEM particles are):
    the threshold keeps the core. Synthetic images identical to the real ones must read 1.0x real; their exact
    labels, which include the rim, would read the particles ~0.5x as bright (a bias the like-for-like masks avoid)."""
    from types import SimpleNamespace

    from drgan.callbacks.fid import FIDCallback, classical_masks, level_ratio, level_sums, levels

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:64, :64]
    radius = np.hypot(yy - 32, xx - 32)
    exact = radius < 14
    clean = np.where(radius < 8, 0.75, np.where(exact, 0.14, 0.1))
    if polarity == "dark":
        clean = 1.0 - clean
    images = np.clip(clean + rng.normal(0, 0.01, (6, 64, 64)), 0, 1).astype(np.float32)
    trainer = SimpleNamespace(datamodule=SimpleNamespace(polarity=polarity, segment=None, real_patches=images))
    real_particle, real_background = FIDCallback().real_levels(trainer)
    seen = levels(level_sums(images, classical_masks(trainer, images)))
    assert level_ratio(seen[0], real_particle, polarity) == pytest.approx(1.0)
    assert level_ratio(seen[1], real_background, polarity) == pytest.approx(1.0)
    masks = classical_masks(trainer, images)
    assert masks[:, radius < 6].all() and not masks[:, (radius > 9) & exact].any()  # the core, not the rim
    by_labels = levels(level_sums(images, np.broadcast_to(exact, images.shape)))
    assert level_ratio(by_labels[0], real_particle, polarity) < 0.6


def test_select_best_treats_nearly_equal_spreads_as_a_tie():
    history = [
        {"epoch": 5, "fid": 140.0, "spread": 0.0197},
        {"epoch": 6, "fid": 148.9, "spread": 0.0200},
        {"epoch": 4, "fid": 142.0, "spread": 0.0170},
    ]
    assert select_best(history, top_k=5)[0]["epoch"] == 5  # within 5 %: the lower FID wins
    assert select_best(history, top_k=5, spread_tolerance=0.0)[0]["epoch"] == 6


def test_select_best_skips_epochs_far_darker_or_brighter_than_real():
    # Epoch 0 has the lowest FID but is 4.6x too dark; epoch 3 is too bright.
    def entry(epoch, fid, spread, level):
        tones = {"particle_brightness": level, "background_brightness": level, "contrast": 2.0}
        return {"epoch": epoch, "fid": fid, "spread": spread, "brightness": level, **tones}

    history = [
        entry(0, 200.0, 0.3, 0.22),
        entry(1, 290.0, 0.1, 0.9),
        entry(2, 300.0, 0.2, 1.1),
        entry(3, 250.0, 0.5, 2.5),
    ]
    assert select_best(history, top_k=5, fid_margin=None)[0]["epoch"] == 3  # no range, no margin: broadest of all
    best, table = select_best(history, top_k=5, brightness_range=(0.5, 2.0))
    assert best["epoch"] == 2 and [h["epoch"] for h in table] == [1, 2]
    assert select_best(history, top_k=1, brightness_range=(0.5, 2.0))[0]["epoch"] == 1
    # None inside the range: all compete rather than nothing being chosen; unknown brightness competes.
    assert select_best(history[:1], top_k=5, brightness_range=(0.5, 2.0))[0]["epoch"] == 0
    assert select_best([{"epoch": 0, "fid": 1.0, "spread": 0.1}], 5, (0.5, 2.0))[0]["epoch"] == 0
    # the particles far too dark on a background of the right grey: out as well
    assert not within_brightness({**entry(4, 1.0, 0.1, 1.0), "particle_brightness": 0.3}, (0.5, 2.0))


def _tem_entry(epoch, fid, fid_std, spread, background):
    tones = {"particle_brightness": 1.0, "background_brightness": background, "contrast": 3.0}
    return {"epoch": epoch, "fid": fid, "fid_std": fid_std, "spread": spread, "brightness": background, **tones}


def test_the_tem_example_a_lower_fid_beyond_its_spread_and_a_real_grey_wins():
    """The issue's TEM run: epoch 1 (FID 132.6, background 0.62 x real) was chosen over epoch 4 (123.1, 1.05 x)
    by its broader parameters, since 132.6 is within 10 % of 123.1 and 0.62 within 0.5-2x."""
    history = [
        _tem_entry(0, 171.0, 2.5, 0.05, 0.50),
        _tem_entry(1, 132.6, 2.0, 0.30, 0.62),
        _tem_entry(2, 141.5, 2.1, 0.12, 0.90),
        _tem_entry(3, 129.9, 1.9, 0.15, 0.95),
        _tem_entry(4, 123.1, 2.0, 0.10, 1.05),
    ]
    # the old rule reproduces the failure
    assert select_best(history, 5, brightness_range=(0.5, 2.0), fid_margin=0.1)[0]["epoch"] == 1
    # the FID's spread alone: 132.6 - 123.1 = 9.5 > 2 x sqrt(2^2 + 2^2) = 5.7, and 129.9 is 6.8 above (> 5.5)
    assert select_best(history, 5, brightness_range=(0.5, 2.0))[0]["epoch"] == 4
    # the derived brightness range alone (TSEM-like: the real backgrounds span 0.70-1.60 x): epoch 1 is out
    derived = {"particle": (0.91, 1.10), "background": (0.70, 1.60)}
    assert not within_brightness(history[1], derived) and within_brightness(history[4], derived)
    assert select_best(history, 5, brightness_range=derived, fid_margin=0.1)[0]["epoch"] == 3
    assert select_best(history, 5, brightness_range=derived)[0]["epoch"] == 4
    # a history without fid_std (written before it existed) keeps the fixed 10 % margin
    old = [{k: v for k, v in h.items() if k != "fid_std"} for h in history]
    assert select_best(old, 5, brightness_range=(0.5, 2.0))[0]["epoch"] == 1


def test_fids_within_their_spread_go_to_the_broader_epoch():
    narrow, broad = {"epoch": 0, "fid": 120.0, "spread": 0.10}, {"epoch": 1, "fid": 124.0, "spread": 0.20}
    # 4 points apart with stds of 3: 4 < 2 x 4.24, indistinguishable, the broader wins
    assert select_best([{**narrow, "fid_std": 3.0}, {**broad, "fid_std": 3.0}], 5)[0]["epoch"] == 1
    # with stds of 1: 4 > 2 x 1.41, the lower FID wins outright
    assert select_best([{**narrow, "fid_std": 1.0}, {**broad, "fid_std": 1.0}], 5)[0]["epoch"] == 0
    # a pair with one std unknown: the fixed 10 % (124 <= 132), the broader wins; an explicit margin ignores stds
    assert select_best([{**narrow, "fid_std": 1.0}, broad], 5)[0]["epoch"] == 1
    assert select_best([{**narrow, "fid_std": 1.0}, {**broad, "fid_std": 1.0}], 5, fid_margin=0.1)[0]["epoch"] == 1
    # an epoch within the lowest's (wide) spread that another epoch beats clearly does not compete either
    history = [
        {"epoch": 0, "fid": 100.0, "fid_std": 10.0, "spread": 0.10},
        {"epoch": 1, "fid": 101.0, "fid_std": 0.5, "spread": 0.20},
        {"epoch": 2, "fid": 110.0, "fid_std": 0.5, "spread": 0.30},  # within 2 x 10.0 of 100, but 9 above 101
    ]
    assert select_best(history, 5)[0]["epoch"] == 1
    assert select_best(history, 5, fid_margin=None)[0]["epoch"] == 2


def test_the_derived_brightness_range_is_the_real_patches_percentiles():
    """21 hand-made patches of 10 pixels, the first 4 particle: particle greys 0.40 .. 0.60 (pooled 0.50), background
    greys 0.10 .. 0.30 (pooled 0.20). numpy's linear percentiles of 21 values: the 5th is the 2nd smallest, the 95th
    the 2nd largest."""
    from drgan.callbacks.fid import brightness_tolerance, level_sums

    particle, background = 0.40 + 0.01 * np.arange(21), 0.10 + 0.01 * np.arange(21)
    mask = np.arange(10) < 4
    images = np.where(mask, particle[:, None], background[:, None])[:, None, :]  # (21, 1, 10)
    masks = np.broadcast_to(mask, images.shape)
    sums = level_sums(images, masks)
    ranges = brightness_tolerance(sums, "bright")
    assert ranges["particle"] == pytest.approx([0.41 / 0.50, 0.59 / 0.50])  # 0.82 - 1.18
    assert ranges["background"] == pytest.approx([0.11 / 0.20, 0.29 / 0.20])  # 0.55 - 1.45
    # dark particles: ratios of the negatives, (1 - 0.59) / 0.5 and (1 - 0.41) / 0.5
    assert brightness_tolerance(sums, "dark")["particle"] == pytest.approx([0.82, 1.18])
    assert brightness_tolerance(sums, "dark")["background"] == pytest.approx([0.71 / 0.80, 0.89 / 0.80])
    # a patch without particle pixels counts for the background only (still 21 particle greys)
    empty = np.full((1, 1, 10), 0.2)
    more = np.concatenate([sums, level_sums(empty, np.zeros(empty.shape, bool))])
    assert brightness_tolerance(more, "bright")["particle"] == pytest.approx(ranges["particle"])
    # a uniform set: the floor, 1/1.1 - 1.1
    uniform = level_sums(np.full((5, 1, 10), 0.5), np.broadcast_to(mask, (5, 1, 10)))
    assert brightness_tolerance(uniform, "bright") == {
        "particle": pytest.approx([1 / 1.1, 1.1]),
        "background": pytest.approx([1 / 1.1, 1.1]),
    }


def test_the_fid_callback_derives_the_range_from_its_real_patches():
    """Disc patches at exposures 0.8 .. 1.2: the classical segmentation's particle and background greys follow."""
    from types import SimpleNamespace

    from drgan.callbacks.fid import FIDCallback

    yy, xx = np.mgrid[:48, :48]
    disc = np.where(np.hypot(yy - 24, xx - 24) < 10, 0.6, 0.2)
    exposure = np.linspace(0.8, 1.2, 21)
    images = (disc[None] * exposure[:, None, None]).astype(np.float32)
    trainer = SimpleNamespace(datamodule=SimpleNamespace(polarity="bright", segment=None, real_patches=images))
    ranges = FIDCallback().brightness_tolerance(trainer)
    expected = [exposure[1] / exposure.mean(), exposure[19] / exposure.mean()]  # 0.82, 1.18
    assert ranges["particle"] == pytest.approx(expected, rel=1e-3)
    assert ranges["background"] == pytest.approx(expected, rel=1e-3)


def _projected(n, seed, power=1.0):
    rng = np.random.default_rng(seed)
    return RandomProjectionFeatures(dim=16).features(rng.random((n, 8, 8)) ** power)


def test_resampled_fid_is_the_fid_on_both_routes():
    from drgan.metrics.feature_distances import FeatureStats, ResampledFID

    real = FeatureStats.from_features(_projected(300, 0))
    for n in (12, 60):  # fewer rows than the 16 features (the N x N route), more (the r x r route)
        feats = _projected(n, 1, power=2.0)
        idx = np.random.default_rng(2).integers(0, n, n)
        resampled = ResampledFID(feats, real)
        assert resampled(np.arange(n)) == pytest.approx(FeatureStats.from_features(feats).fid(real), rel=1e-9)
        assert resampled(idx) == pytest.approx(FeatureStats.from_features(feats[idx]).fid(real), rel=1e-9)


def test_the_bootstrap_fid_std_is_the_fids_spread_and_shrinks_with_more_images():
    from drgan.metrics.feature_distances import FeatureStats, fid_bootstrap_std

    real = FeatureStats.from_features(_projected(400, 0))
    small, large = (fid_bootstrap_std(_projected(n, 1, power=2.0), real) for n in (40, 640))
    assert small > 0 and large > 0
    assert large < 0.5 * small  # ~1 / sqrt(N): 4x fewer expected at 16x the images
    assert fid_bootstrap_std(_projected(40, 1, power=2.0), real, seed=3) == pytest.approx(
        fid_bootstrap_std(_projected(40, 1, power=2.0), real, seed=3)
    )
    # on average it is the std of the FID over independent samples of the generated images
    fids = [FeatureStats.from_features(_projected(40, s, power=2.0)).fid(real) for s in range(100, 300)]
    bootstrap = np.mean([fid_bootstrap_std(_projected(40, s, power=2.0), real) for s in range(100, 120)])
    assert bootstrap == pytest.approx(np.std(fids, ddof=1), rel=0.3)
    with pytest.raises(ConfigError, match="resamples"):
        fid_bootstrap_std(_projected(40, 1), real, resamples=1)


@pytest.mark.parametrize("bad", [[2.0, 0.5], [0.0, 1.0], [1.0], "bright", [0.5, "x"], {"low": 0.5}, 1.5, True])
def test_best_epoch_refuses_bad_brightness_range(bad):
    from drgan.callbacks import BestEpochCallback

    with pytest.raises(ConfigError, match=r"callbacks\.best_epoch\.brightness_range"):
        BestEpochCallback(brightness_range=bad)


@pytest.mark.parametrize("bad", [-0.1, "tight", True, float("inf"), [0.1]])
def test_best_epoch_refuses_bad_fid_margin(bad):
    from drgan.callbacks import BestEpochCallback

    with pytest.raises(ConfigError, match=r"callbacks\.best_epoch\.fid_margin"):
        BestEpochCallback(fid_margin=bad)


@pytest.mark.parametrize("bad", [1, -1, 2.5, True, "10"])
def test_fid_callback_refuses_bad_fid_resamples(bad):
    from drgan.callbacks import FIDCallback

    with pytest.raises(ConfigError, match=r"callbacks\.fid\.fid_resamples"):
        FIDCallback(fid_resamples=bad)


def test_best_epoch_accepts_auto_null_and_a_config_list():
    from omegaconf import OmegaConf

    from drgan.callbacks import BestEpochCallback

    assert BestEpochCallback().brightness_setting == "auto" and BestEpochCallback().fid_margin == "auto"
    fixed = BestEpochCallback(brightness_range=OmegaConf.create([0.6, 1.5]), fid_margin=0)
    assert fixed.brightness_range == (0.6, 1.5) and fixed.fid_margin == 0.0
    assert BestEpochCallback(brightness_range=None, fid_margin=None).brightness_range is None


def test_parameter_spread_hand_computed():
    # parameter a in [0, 2]: values 0, 2 -> unit 0, 1 -> std 0.5; b in [1, 3]: 2, 2 -> std 0
    values = np.array([[0.0, 2.0], [2.0, 2.0]])
    assert parameter_spread(values, [0.0, 1.0], [2.0, 3.0]) == pytest.approx(0.25)
    assert parameter_spread(np.full((5, 3), 0.3), [0, 0, 0], [1, 1, 1]) == 0.0
    with pytest.raises(ConfigError, match="do not match limits"):
        parameter_spread(values, [0.0], [1.0])


@pytest.mark.slow  # two trainings and a resume: ~20 s (the default run's longest)
def test_training_with_callbacks_writes_best_epoch_metrics_plots_and_resumes(images, tmp_path):  # noqa: F811
    import mlflow

    uri = f"sqlite:///{tmp_path}/mlruns/mlflow.db"
    out = tmp_path / "run"
    base = tiny_overrides(
        images, out, logger="mlflow", extra=[f"logger.mlflow.tracking_uri={uri}", "trainer.limit_train_batches=1"]
    )
    metrics = run_train(base + ["trainer.max_epochs=2"])
    assert np.isfinite(metrics["val/fid"]) and np.isfinite(metrics["val/kid"]) and metrics["time/fid_s"] > 0

    ckpts = out / "checkpoints"
    summary = json.loads((ckpts / "best_epoch.json").read_text())
    assert [h["epoch"] for h in summary["history"]] == [0, 1]
    assert summary["epoch"] in (0, 1) and (ckpts / "best.ckpt").is_file()
    assert all(0.0 <= h["spread"] <= 0.5 for h in summary["history"])
    assert all(h["brightness"] > 0 for h in summary["history"])
    # brightness_range auto: the range the real patches span, at least 1/1.1 - 1.1, for particles and background
    assert summary["brightness_range_setting"] == "auto" and summary["fid_margin"] == "auto"
    for low, high in (summary["brightness_range"][k] for k in ("particle", "background")):
        assert 0 < low <= 1 / 1.1 and high >= 1.1
    assert all(h["fid_std"] > 0 for h in summary["history"])  # the FID's bootstrap std, for the rule
    # the guard sees particles and background apart, and the contrast's direction (bright particles here)
    assert all(
        h["particle_brightness"] > 0 and h["background_brightness"] > 0 and h["contrast"] > 0
        for h in summary["history"]
    )
    for name in (
        "params_epoch_000.png",
        "params_epoch_001.png",
        "samples_epoch_000.png",
        "samples_epoch_001.png",
        "fid.png",
    ):
        assert (out / "plots" / name).is_file(), name
    assert list((out / "fid_cache").glob("real_*_RandomProjectionFeatures_clean_24x24.npz"))
    # ModelCheckpoint monitors val/fid: it found the metric (else it raises) and kept a best model.
    assert (ckpts / "last.ckpt").is_file()

    from drgan.models.gan_module import GANModule

    best = GANModule.load_from_checkpoint(ckpts / "best.ckpt", weights_only=True)
    assert best.phi_bank.shape[1:] == (3, 4)

    client = mlflow.MlflowClient(tracking_uri=uri)
    run_id = (out / "mlflow_run_id.txt").read_text()
    run = client.get_run(run_id)
    for key in ("val/fid", "val/kid", "val/brightness", "time/fid_s", "best/epoch", "best/fid"):
        assert key in run.data.metrics, key
    assert len(client.get_metric_history(run_id, "val/fid")) == 2
    artifacts = {a.path for a in client.list_artifacts(run_id)} | {
        a.path for a in client.list_artifacts(run_id, "plots")
    }
    assert "best_epoch.json" in artifacts and "plots/samples_epoch_001.png" in artifacts

    # Resume for a third epoch: the FID history of the first two is kept.
    run_train(base + ["trainer.max_epochs=3", "ckpt_path=last"])
    summary = json.loads((ckpts / "best_epoch.json").read_text())
    assert [h["epoch"] for h in summary["history"]] == [0, 1, 2]
    assert len(client.get_metric_history(run_id, "val/fid")) == 3


def test_random_projection_features_are_fixed():
    imgs = np.random.default_rng(0).random((3, 8, 8))
    a, b = RandomProjectionFeatures(dim=5).features(imgs), RandomProjectionFeatures(dim=5).features(imgs)
    assert a.shape == (3, 5) and np.array_equal(a, b)


def test_fid_settings_that_cannot_work_fail_before_the_data_are_mined(tmp_path, monkeypatch):
    from test_train import make_images, run_train, tiny_overrides

    import drgan.data.datamodule as dm

    monkeypatch.setattr(
        dm, "mine_patches", lambda *a, **k: pytest.fail("patches mined before the FID settings were checked")
    )
    folder = make_images(tmp_path / "images", n=3, size=40, seed=2)
    with pytest.raises(ConfigError, match=r"kid_subset_size=9 exceeds callbacks.fid.n_images=4"):
        run_train(tiny_overrides(folder, tmp_path / "run", extra=["+callbacks.fid.kid_subset_size=9"]))
    # the Inception network's file is read and its hash checked before mining too
    from drgan.core.errors import DataError

    bad = tmp_path / "inception.pt"
    bad.write_bytes(b"not the network")
    overrides = [o for o in tiny_overrides(folder, tmp_path / "run2") if not o.startswith("callbacks.fid.extractor")]
    with pytest.raises(DataError, match="SHA-256"):
        run_train(
            overrides
            + [f"callbacks.fid.extractor={{_target_:drgan.metrics.inception.InceptionFeatures,weights_path:{bad}}}"]
        )


def test_a_kid_subset_larger_than_the_mined_patches_stops_before_the_first_step(tmp_path, monkeypatch):
    import lightning.pytorch as L
    from test_train import make_images, run_train, tiny_overrides

    monkeypatch.setattr(
        L.LightningModule, "training_step", lambda *a, **k: pytest.fail("trained with an impossible KID")
    )
    folder = make_images(tmp_path / "images", n=3, size=40, seed=2)
    with pytest.raises(ConfigError, match=r"kid_subset_size=500 exceeds the \d+ images of each KID sample"):
        run_train(
            tiny_overrides(
                folder, tmp_path / "run", extra=["+callbacks.fid.kid_subset_size=500", "callbacks.fid.n_images=null"]
            )
        )


def test_an_evaluations_log_line_gives_its_scores_or_says_the_screen_left_it_out(caplog):
    import logging
    import math

    from drgan.callbacks.fid import FIDCallback

    entry = {"epoch": 3, "fid": 110.84, "fid_std": 2.5, "kid": 0.1116, "brightness": 0.81, "particle_brightness": 1.02,
             "background_brightness": 0.78, "contrast": 4.9, "n_images": 128, "seconds": 81.2}  # fmt: skip
    with caplog.at_level(logging.INFO, logger="drgan.callbacks.fid"):
        FIDCallback()._log_line(entry, "bright")
        FIDCallback(screen_margin=0.2)._log_line({**entry, "fid": math.nan, "screen_kid": 0.2, "n_images": 48}, "dark")
    full, screened = caplog.messages[-2:]
    assert full == (
        "epoch 3: FID 110.8 (bootstrap std 2.5), KID 0.1116, brightness 0.81 x real (particles 1.02 x, background "
        "0.78 x, contrast 4.90 for bright particles; 128 images, 81.2 s)"
    )
    assert screened == (
        "epoch 3: screened out (KID of 48 images 0.2, above the lowest so far by more than 20 %): no full FID (81.2 s)"
    )
