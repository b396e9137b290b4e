"""drgan.generate and drgan.export_nnunet on a tiny checkpoint (24 px, spp 1, 3 particles, 1 training step).

The tiny generator is untrained, so most tests keep every image with a visible particle (min_contrast=0);
the contrast filter itself is tested on hand-made arrays and by a filter that nothing passes.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import compose
from PIL import Image
from test_train import make_images, run_train, tiny_overrides

from drgan import generate as gen
from drgan.core.errors import ConfigError
from drgan.synthetic.generation_settings import GenerateSettings, defaults, setting

N = 3
N_BG = 2


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """A training run folder with checkpoints/best.ckpt and patches/ (2 background patches)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        root = tmp_path_factory.mktemp("gen")
        images = make_images(root / "real" / "images")
        out = root / "run"
        run_train(tiny_overrides(images, out, extra=["trainer.max_epochs=1", "trainer.limit_train_batches=1"]))
    finally:
        torch.set_num_threads(threads)
    assert (out / "checkpoints" / "best.ckpt").is_file() and (out / "patches" / "patches.npz").is_file()
    return out


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def run_generate(ckpt, out, *extra, n=N, n_background=N_BG):
    cfg = compose(
        [
            f"ckpt={ckpt}", f"out={out}", f"n={n}", f"n_background={n_background}", "min_contrast=0",
            "progress=false", *extra,
        ],
        config_name="generate",
    )  # fmt: skip
    return gen.generate(cfg)


@pytest.fixture
def count_renders(monkeypatch):
    calls = []
    render = gen.render_index

    def counting(module, sample_phi, settings, index, *rest):
        calls.append(index)
        return render(module, sample_phi, settings, index, *rest)

    monkeypatch.setattr(gen, "render_index", counting)
    return calls


@pytest.fixture(scope="session")
def dataset(tiny_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("syn") / "data"
    run_generate(tiny_run, out)
    return out


def read(path) -> np.ndarray:
    return np.asarray(Image.open(path))


def ids(out: Path) -> list[str]:
    return [e["id"] for e in json.loads((out / "manifest.json").read_text())["entries"]]


# --- units --------------------------------------------------------------------------------------------------


def test_pairs_pixel_scale_is_the_render_over_the_real_window_the_gan_learned_from(tmp_path):
    from drgan.data.patches import PatchSet

    assert gen.pairs_pixel_scale(256, None, 256.0) == 1.0  # no patch set (an imported generator): its view
    assert gen.pairs_pixel_scale(256, tmp_path / "none", 512.0) == 0.5
    (tmp_path / "wide").mkdir()
    (tmp_path / "wide" / "summary.json").write_text(json.dumps({"params": {"size": 256, "window": 512}}))
    assert (
        PatchSet.saved_window(tmp_path / "wide") == 512 and gen.pairs_pixel_scale(256, tmp_path / "wide", 256.0) == 0.5
    )
    (tmp_path / "same").mkdir()
    (tmp_path / "same" / "summary.json").write_text(json.dumps({"params": {"size": 24}}))  # windows of the render size
    assert gen.pairs_pixel_scale(24, tmp_path / "same", 256.0) == 1.0


def test_contrast_check_hand_made():
    labels = np.zeros((10, 10), np.int32)
    labels[2:5, 2:5] = 1
    labels[6:8, 6:8] = 2
    image = np.full((10, 10), 0.2)
    image[labels > 0] = 0.3  # 1.5 x the background
    check = gen.contrast_check(image, labels, 1.15, 0.05)
    assert check.kept and check.contrast == pytest.approx(1.5) and check.particles_visible == 2
    assert check.background_fraction == pytest.approx(87 / 100)
    image[labels > 0] = 0.22  # 1.1 x: not clearly brighter
    assert gen.contrast_check(image, labels, 1.15, 0.05).reason == "contrast"
    assert gen.contrast_check(image, np.zeros_like(labels), 1.15, 0.05).reason == "no_particle"
    assert gen.contrast_check(image, np.ones_like(labels), 0.0, 0.05).reason == "background_fraction"
    labels[:, :] = 1
    labels[0, :3] = 0  # 3 % background < 5 %
    assert gen.contrast_check(np.ones((10, 10)), labels, 0.0, 0.05).reason == "background_fraction"


def test_contrast_check_for_dark_particles_asks_for_a_darker_particle_by_the_same_factor():
    labels = np.zeros((10, 10), np.int32)
    labels[2:5, 2:5] = 1
    image = np.full((10, 10), 0.6)
    image[labels > 0] = 0.4  # the background is 1.5 x the particles
    dark = gen.contrast_check(image, labels, 1.15, 0.05, polarity="dark")
    assert dark.kept and dark.contrast == pytest.approx(1.5)
    bright = gen.contrast_check(image, labels, 1.15, 0.05)  # the same image judged as bright particles: inverted
    assert bright.reason == "contrast" and bright.contrast == pytest.approx(0.4 / 0.6)
    image[labels > 0] = 0.55  # 1.09 x: not clearly darker
    assert gen.contrast_check(image, labels, 1.15, 0.05, polarity="dark").reason == "contrast"
    with pytest.raises(ConfigError, match="polarity='grey'"):
        gen.contrast_check(image, labels, 1.15, 0.05, polarity="grey")


def test_shard_and_seeds():
    from drgan.synthetic.shards import Shard, dataset_cutoff

    assert Shard.parse("1/3") == Shard(1, 3) and Shard.parse(None) == Shard(0, 1)
    for bad in ("3/2", "2/2", "-1/2", "1/0", "a/b", "1", "1/2/3"):
        with pytest.raises(ConfigError, match="expected 'i/k'"):
            Shard.parse(bad)
    assert gen.index_seeds(0, 5) == gen.index_seeds(0, 5) != gen.index_seeds(0, 6) != gen.index_seeds(1, 5)
    assert dataset_cutoff({0: True, 1: False, 2: True, 4: True}, 2) == (2, 3)
    assert dataset_cutoff({0: True, 1: False, 3: True}, 2) == (None, 2)


def test_generate_yaml_and_the_settings_dataclass_hold_the_same_defaults():
    """conf/gan/generate.yaml is the user's reference and GenerateSettings the code's: they cannot drift apart."""
    from omegaconf import OmegaConf

    cfg = compose([], config_name="generate")
    given = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert set(given) <= set(defaults()), "a key of generate.yaml that GenerateSettings lacks"
    assert all(v is None for v in given.pop("renderer").values())  # overrides; null = the checkpoint's
    assert given == {key: defaults()[key] for key in given}  # every YAML value as the field's default
    assert defaults()["renderer"] == {} and defaults()["material"] is None  # groups: nothing asked for
    composed = compose(["ckpt=run", "out=data"], config_name="generate")
    assert GenerateSettings.from_config(composed) == GenerateSettings(ckpt="run", out="data")


def test_a_setting_is_checked_naming_its_key_before_anything_is_read():
    for override, message in (
        ("n=0", r"n=0: expected an integer >= 1"),
        ("min_background=1.0", r"min_background=1.0: expected a fraction below 1"),
        ("contour_px=1.5", r"contour_px=1.5: expected an integer >= 0"),
        ("grey_spread=maybe", r"grey_spread='maybe': expected auto, true or false"),
        ("max_attempts=2", r"max_attempts=2: expected >= n=1000"),
        ("seed=abc", r"seed='abc': expected an integer"),
    ):
        with pytest.raises(ConfigError, match=message):
            GenerateSettings.from_config(compose(["ckpt=/nope", "out=data", override], config_name="generate"))
    settings = GenerateSettings.from_config(compose(["ckpt=/nope", "out=data", "n=3"], config_name="generate"))
    assert (settings.max_attempts, settings.shard, settings.min_contrast) == (130, "0/1", 1.15)


def test_a_new_setting_is_one_field_and_reaches_the_stage(tiny_run, tmp_path, monkeypatch):
    """CONTRIBUTING's recipe for a new generate key: a field of GenerateSettings (type, default, check) and, where
    users should see it, its line in generate.yaml. A subclass stands in for the edited class, ``+toy_gain=`` for
    the YAML line; without it the field's default applies."""

    @dataclass(frozen=True, kw_only=True)
    class ToySettings(GenerateSettings):
        toy_gain: float = setting(1.0, gt=0.0)  # a toy key, fixed by config.json when not at its default (CHANGED)

    seen = []
    render = gen.render_index

    def spy(module, sample_phi, settings, index, *rest):
        seen.append(settings.toy_gain)
        return render(module, sample_phi, settings, index, *rest)

    monkeypatch.setattr(gen, "render_index", spy)
    out = tmp_path / "data"
    args = [f"ckpt={tiny_run}", f"out={out}", "n=1", "n_background=0", "min_contrast=0", "progress=false"]
    manifest = gen.generate_dataset(ToySettings.from_config(compose([*args, "+toy_gain=2.5"], "generate")))
    assert seen and set(seen) == {2.5}
    assert manifest["config"]["toy_gain"] == 2.5 and list(manifest["config"])[-1] == "toy_gain"
    assert json.loads((out / "config.json").read_text())["fixed"]["toy_gain"] == 2.5
    with pytest.raises(ConfigError, match=r"generated with other settings \(toy_gain: 2.5 there, None now\)"):
        gen.generate_dataset(ToySettings.from_config(compose(args, "generate")))  # the default, 1.0: not recorded
    for bad in ("-1", "many"):
        with pytest.raises(ConfigError, match=rf"generate: toy_gain='?{bad}'?: expected a number > 0"):
            ToySettings.from_config(compose([*args, f"+toy_gain={bad}"], "generate"))


def test_sampled_spp_replaces_the_spp_where_renders_carry_sampling_noise_only(tiny_run, tmp_path):
    """Secondary-electron renders speckle at a low spp (the real images do not), transmission renders are noiseless:
    ``sampled_spp`` sets the spp of the first and leaves the second at renderer.spp."""
    from drgan.scene.config import typed_material

    args = [f"ckpt={tiny_run}", f"out={tmp_path / 'data'}", "renderer.spp=2"]
    plain = GenerateSettings.from_config(compose(args, "generate")).resolve()
    sampled = GenerateSettings.from_config(compose([*args, "sampled_spp=5"], "generate")).resolve()
    assert not plain.material.imaging.noiseless  # the tiny run's material: secondary electrons
    assert plain.settings.renderer["spp"] == 2 and sampled.settings.renderer["spp"] == 5
    assert sampled.model_cfg["renderer"]["spp"] == 5 and sampled.settings.record()["sampled_spp"] == 5
    assert sampled.settings.fixed()["sampled_spp"] == 5 and "sampled_spp" not in plain.settings.fixed()
    tem = typed_material(compose(["material=tio2_tsem"], config_name="train").material)
    settings = GenerateSettings.from_config(compose([*args, "sampled_spp=5"], "generate"))
    assert tem.imaging.noiseless and settings._renderer_for(tem) == {"spp": 2}
    with pytest.raises(ConfigError, match=r"sampled_spp=0: expected an integer >= 1"):
        GenerateSettings.from_config(compose([*args, "sampled_spp=0"], "generate"))


# --- generation ---------------------------------------------------------------------------------------------


def test_dataset_layout_masks_and_manifest(dataset):
    manifest = json.loads((dataset / "manifest.json").read_text())
    syn = [e for e in manifest["entries"] if e["kind"] == "synthetic"]
    bg = [e for e in manifest["entries"] if e["kind"] == "background"]
    assert len(syn) == N and [e["id"] for e in bg] == ["bg_0000", "bg_0001"]
    assert all(e["id"] == f"syn_{e['index']:06d}" for e in syn)
    counts = manifest["counts"]
    assert counts["kept"] == N and counts["attempted"] == N + counts["dropped"]
    assert manifest["config"]["material"] == "tio2_sem" and manifest["config"]["renderer"]["spp"] == 1
    assert manifest["config"]["contour_px"] == 1 and manifest["throughput"]["this_run"]["rendered"] >= N
    assert manifest["pixel_scale"] == 1.0  # rendered at the px of the windows the GAN learned from
    # what the material knows of the real particles: tio2_sem is written by hand, its arrangement not measured
    assert manifest["material"] == {"name": "tio2_sem", "clark_evans": None}
    for entry in manifest["entries"]:
        files = {k: dataset / v for k, v in entry["files"].items()}
        image, mask, labels = read(files["image"]), read(files["mask"]), read(files["label"])
        assert image.dtype == np.uint8 and image.shape == mask.shape == labels.shape == (24, 24)
        assert set(np.unique(mask)) <= {0, 1, 2}
        np.testing.assert_array_equal(mask > 0, labels > 0)
        meta = json.loads(files["meta"].read_text())
        if entry["kind"] == "background":
            assert not mask.any() and meta["source"]["image_id"].startswith("img")
        else:
            assert labels.any() and np.asarray(meta["phi"]).shape == (3, 4)
            assert meta["sigma"] is not None and meta["contrast"] > 0 and set(meta["seed"]) == {"phi", "render"}
    # The noise check against the run's real train patches (drgan.synthetic.noise_check), on every image kept.
    noise = json.loads((dataset / "noise_check.json").read_text())
    assert noise["images"]["generated"] == N and noise["highpass_px"] == 1.0
    assert noise["background"]["ratio"] is not None  # 24 px renders leave background enough beyond the margin
    for name in ("background", "particles"):
        row = noise[name]
        assert set(row) == {"real", "generated", "ratio"}
        if row["ratio"] is not None:
            assert row["ratio"] == pytest.approx(row["generated"] / row["real"], rel=1e-2)
    # The edge check (drgan.synthetic.edge_check): written with its figure; 24 px renders hold no isolated particle
    # with the background ring the profile needs, so its sides may be empty, but never half-written
    edges = json.loads((dataset / "edge_check.json").read_text())
    assert set(edges) >= {"real", "generated", "generated_mask", "half_px_difference", "width_ratio", "images"}
    assert edges["images"]["generated"] == N and (dataset / "edge_check.png").is_file()
    # The contact check (drgan.synthetic.contact_check): written whole; tiny renders may hold no contact to measure
    contacts = json.loads((dataset / "contact_check.json").read_text())
    assert set(contacts) == {"real", "generated", "generated_exact", "hidden_difference", "polarity", "images"}
    assert contacts["images"]["generated"] == N
    # Nothing half-written: no temporary files anywhere.
    assert not [p for p in dataset.rglob("*") if p.name.startswith(".") or ".tmp" in p.name]


def test_resume_skips_done_indices_and_completes(tiny_run, dataset, tmp_path, count_renders):
    out = tmp_path / "data"
    shutil.copytree(dataset, out)
    first = ids(out)[0]
    reference = (out / "images" / f"{first}.png").read_bytes()
    # A cut-off run: the first image lost its meta (the done marker) and its image.
    (out / "meta" / f"{first}.json").unlink()
    (out / "images" / f"{first}.png").unlink()
    (out / "manifest.json").unlink()
    run_generate(tiny_run, out)
    assert count_renders == [int(first[4:])]  # only the unfinished index is rendered again ...
    assert (out / "images" / f"{first}.png").read_bytes() == reference  # ... and it is the same image
    assert ids(out) == ids(dataset)
    # The same command again renders nothing; a larger n renders only the new indices.
    count_renders.clear()
    run_generate(tiny_run, out)
    assert count_renders == []
    run_generate(tiny_run, out, n=N + 1)
    assert count_renders and min(count_renders) > max(int(i[4:]) for i in ids(dataset) if i.startswith("syn"))
    assert len([i for i in ids(out) if i.startswith("syn")]) == N + 1


def test_two_shards_fill_one_dataset_like_one_process(tiny_run, dataset, tmp_path):
    out = tmp_path / "data"
    run_generate(tiny_run, out, "shard=0/2")  # alone, it goes on until n are kept below its next index
    run_generate(tiny_run, out, "shard=1/2")
    assert (out / "manifest_shard_0.json").is_file() and (out / "manifest_shard_1.json").is_file()
    assert ids(out) == ids(dataset)
    for entry in ids(dataset):
        assert (out / "images" / f"{entry}.png").read_bytes() == (dataset / "images" / f"{entry}.png").read_bytes()
    # merge=true renders nothing and writes the same manifest.
    (out / "manifest.json").unlink()
    run_generate(tiny_run, out, "merge=true")
    assert ids(out) == ids(dataset)


def test_filter_that_nothing_passes_stops_with_a_clear_error(tiny_run, tmp_path):
    with pytest.raises(RuntimeError, match=r"only 0 of n=1 images passed the filter in max_attempts=2"):
        run_generate(tiny_run, tmp_path / "data", "min_contrast=1e9", "max_attempts=2", "n_background=0", n=1)
    assert len(list((tmp_path / "data" / "dropped").glob("syn_*.json"))) == 2


def test_a_run_whose_first_images_all_fail_the_filter_stops_early_and_says_why(tiny_run, tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "EARLY_ATTEMPTS", 3)
    with pytest.raises(
        RuntimeError,
        match=r"none of the first 3 images passed the filter .*median contrast .* for dark "
        r"particles.*wrong side of the background",
    ):
        run_generate(tiny_run, tmp_path / "data", "min_contrast=1e9", "polarity=dark", "n_background=0", n=50)
    assert len(list((tmp_path / "data" / "dropped").glob("syn_*.json"))) == 3


@pytest.mark.parametrize(
    "case, extra, message",
    [
        ("missing", ["ckpt=/nope/best.ckpt"], "no such checkpoint file or run folder"),
        ("n0", ["n=0"], r"n=0: expected an integer >= 1"),
        ("shard", ["shard=3/2"], "expected 'i/k'"),
        ("material", ["material=tio2_him"], r"was trained for material tio2_sem, not tio2_him"),
        ("settings", ["seed=7"], "generated with other settings"),
        ("placement", ["placement=poisson", "placement.min_distance_factor=-1"], "min_distance_factor"),
        ("size", ["size=normal", "+size.spread=2"], "spread"),
    ],
)
def test_bad_inputs_fail_before_rendering(case, extra, message, tiny_run, dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "load_module", lambda *a, **k: pytest.fail("model loaded before the inputs were checked"))
    out = dataset if case == "settings" else tmp_path / "data"
    args = [f"ckpt={tiny_run}", f"out={out}", "progress=false", *extra]
    with pytest.raises(ConfigError, match=message):
        gen.generate(compose(args, config_name="generate"))


def test_a_size_and_placement_given_replace_the_checkpoints_and_keep_the_folder(tiny_run, tmp_path):
    """`size=` / `placement=` on generate's command line: the trained generator renders the constellations given
    (their ${material.*} read from the checkpoint's material), manifest.json records them, and the folder is only
    completed with the same ones."""
    out = tmp_path / "data"
    given = ["size=normal", "size.mean=7.5", "size.std=0", "placement=random_2d", "placement.margin=1.0"]
    manifest = run_generate(tiny_run, out, *given, n_background=0)
    assert manifest["config"]["size"]["mean"] == 7.5 and manifest["config"]["placement"]["margin"] == 1.0
    for meta in sorted((out / "meta").glob("syn_*.json")):
        phi = np.asarray(json.loads(meta.read_text())["phi"])
        phi = phi[phi[:, 3] > 0]  # the particles drawn (rows beyond n are zero)
        assert len(phi) and np.allclose(phi[:, 3], 7.5)  # every diameter the one given
        assert np.allclose(phi[:, 2], 7.5 / 2)  # random_2d: resting on the stage
    with pytest.raises(ConfigError, match="generated with other settings"):
        run_generate(tiny_run, out, n_background=0)  # the checkpoint's constellations: another dataset
    default = run_generate(tiny_run, tmp_path / "default", n_background=0)
    assert default["config"]["size"] is None and default["config"]["placement"] is None


# --- partial backgrounds: real windows with particles, which their masks ignore ---------------------------------

N_PARTIAL = 2  # n_background=N_BG + N_PARTIAL: the tiny run's PatchSet holds only N_BG windows free of particles


@pytest.fixture(scope="session")
def partial_dataset(tiny_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("partial") / "data"
    run_generate(tiny_run, out, n=1, n_background=N_BG + N_PARTIAL)
    return out


def test_partial_backgrounds_fill_up_and_ignore_the_real_particles(tiny_run, partial_dataset):
    from drgan.data.patches import PatchSet

    patches = PatchSet.load(tiny_run / "patches")
    assert len(patches.background) == N_BG and len(patches.train) > N_PARTIAL
    manifest = json.loads((partial_dataset / "manifest.json").read_text())
    assert manifest["counts"]["background"] == N_BG and manifest["counts"]["partial_background"] == N_PARTIAL
    assert manifest["config"]["partial_background"] is True and manifest["partial_backgrounds"]["count"] == N_PARTIAL
    partial = [e for e in manifest["entries"] if e["kind"] == "partial_background"]
    assert [e["id"] for e in partial] == ["pbg_0000", "pbg_0001"]
    real = tiny_run.parent / "real" / "images"  # make_images: discs of grey 0.8 on a background of 0.15
    for entry in partial:
        files = {k: partial_dataset / v for k, v in entry["files"].items()}
        meta = json.loads(files["meta"].read_text())
        mask = read(files["mask"])
        assert mask.shape == (24, 24) and set(np.unique(mask).tolist()) == {0, 255}
        r, c = meta["source"]["position"]
        source = read(real / f"{meta['source']['image_id']}.png")[r : r + 24, c : c + 24]
        np.testing.assert_array_equal(read(files["image"]), source)  # the real window, as it is
        assert (mask[source > 127] == 255).all()  # every seeded disc pixel is ignored, none called background
        assert 0 < meta["ignored_fraction"] <= 0.6 and meta["margin_px"] == 3 and not read(files["label"]).any()


def test_partial_backgrounds_resume_and_refuse_other_settings(tiny_run, partial_dataset, tmp_path, count_renders):
    out = tmp_path / "data"
    shutil.copytree(partial_dataset, out)
    reference = (out / "masks" / "pbg_0001.png").read_bytes()
    (out / "meta" / "pbg_0001.json").unlink()  # cut off while writing it
    (out / "manifest.json").unlink()
    run_generate(tiny_run, out, n=1, n_background=N_BG + N_PARTIAL)
    assert count_renders == [] and (out / "masks" / "pbg_0001.png").read_bytes() == reference
    assert ids(out) == ids(partial_dataset)
    for extra in ("partial_background=false", "partial_max_ignored=0.3", "partial_margin_px=1"):
        with pytest.raises(ConfigError, match=rf"generated with other settings \({extra.split('=')[0]}: None there"):
            run_generate(tiny_run, out, extra, n=1, n_background=N_BG + N_PARTIAL)
    with pytest.raises(ConfigError, match=r"partial_max_ignored=1.5: expected a fraction in \[0, 1\]"):
        run_generate(tiny_run, tmp_path / "other", "partial_max_ignored=1.5")


# --- nnU-Net export -----------------------------------------------------------------------------------------


def export(data, out, *extra):
    from drgan.export_nnunet import ExportSettings, compose_config
    from drgan.export_nnunet import export as run

    return run(ExportSettings.from_config(compose_config([f"data={data}", f"out={out}", *extra])))


def test_export_nnunet_layout_and_dataset_json(dataset, tmp_path):
    target = export(dataset, tmp_path / "raw")
    assert target.name == "Dataset501_TiO2SEM"
    description = json.loads((target / "dataset.json").read_text())
    assert description["channel_names"] == {"0": "SEM"} and description["file_ending"] == ".png"
    assert description["labels"] == {"background": 0, "particle": 1, "contour": 2}
    assert description["numTraining"] == N + N_BG
    cases = ids(dataset)
    assert sorted(p.name for p in (target / "imagesTr").iterdir()) == sorted(f"{c}_0000.png" for c in cases)
    assert sorted(p.name for p in (target / "labelsTr").iterdir()) == sorted(f"{c}.png" for c in cases)
    assert (target / "labelsTr" / f"{cases[0]}.png").read_bytes() == (
        dataset / "masks" / f"{cases[0]}.png"
    ).read_bytes()
    # The same export again is fine; a different dataset under the same id or folder is refused.
    export(dataset, tmp_path / "raw")
    with pytest.raises(ConfigError, match="holds a different dataset"):
        export(dataset, tmp_path / "raw", "channel_names.0=HIM")
    with pytest.raises(ConfigError, match="already holds Dataset501_TiO2SEM"):
        export(dataset, tmp_path / "raw", "name=Other")
    assert not [p for p in target.rglob("*") if ".tmp" in p.name]


def test_export_nnunet_passes_nnunet_integrity_check(dataset, tmp_path):
    try:  # the nnunet extra, which `make setup` installs: never skipped
        from nnunetv2.experiment_planning.verify_dataset_integrity import verify_dataset_integrity
    except ImportError as err:
        pytest.fail(f"nnunetv2 is not installed ({err}): run `make setup` or pip install -e '.[nnunet]'")

    target = export(dataset, tmp_path / "raw")
    verify_dataset_integrity(str(target), num_processes=1)
    # The check itself can fail: a label value outside dataset.json's labels is refused.
    label = target / "labelsTr" / f"{ids(dataset)[0]}.png"
    mask = np.asarray(Image.open(label)).copy()
    mask[0, 0] = len(json.loads((target / "dataset.json").read_text())["labels"])  # labels are 0..K-1
    Image.fromarray(mask).save(label)
    with pytest.raises(RuntimeError, match="unexpected labels"):
        verify_dataset_integrity(str(target), num_processes=1)


def test_export_nnunet_declares_the_ignore_label_for_partial_backgrounds(partial_dataset, tmp_path):
    from nnunetv2.experiment_planning.verify_dataset_integrity import verify_dataset_integrity

    from drgan.core.errors import DataError

    target = export(partial_dataset, tmp_path / "raw")
    description = json.loads((target / "dataset.json").read_text())
    # nnU-Net v2: the ignore label is the highest label value, named "ignore".
    assert description["labels"] == {"background": 0, "particle": 1, "contour": 2, "ignore": 3}
    assert f"+ {N_PARTIAL} real partial backgrounds" in description["description"]
    for case in ids(partial_dataset):
        label, mask = read(target / "labelsTr" / f"{case}.png"), read(partial_dataset / "masks" / f"{case}.png")
        np.testing.assert_array_equal(label, np.where(mask == 255, 3, mask))
        if not case.startswith("pbg_"):  # masks without the ignore value are copied byte for byte
            assert (target / "labelsTr" / f"{case}.png").read_bytes() == (
                partial_dataset / "masks" / f"{case}.png"
            ).read_bytes()
    verify_dataset_integrity(str(target), num_processes=1)
    export(partial_dataset, tmp_path / "raw")  # the same export again is fine

    with pytest.raises(ConfigError, match="ignore label must be the highest value"):
        export(partial_dataset, tmp_path / "raw2", "+labels.ignore=1", "labels.particle=2", "labels.contour=3")
    data = tmp_path / "data"
    shutil.copytree(partial_dataset, data)
    mask = read(data / "masks" / "pbg_0000.png").copy()
    mask[0, 0] = 7
    Image.fromarray(mask).save(data / "masks" / "pbg_0000.png")
    with pytest.raises(DataError, match=r"mask .*masks/pbg_0000.png: values \[7\] are none of labels"):
        export(data, tmp_path / "raw3")
    assert not (tmp_path / "raw3").exists()  # refused before anything is written


def test_export_and_segment_read_the_dataset_through_its_manifest(dataset, tmp_path):
    from drgan.core.errors import DataError
    from drgan.segmenters.pairs import load_generated_pairs

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    extra = "syn_999999"  # kept on disk beyond the n-th (a shard's surplus): not in the manifest
    for kind in ("images", "masks", "labels"):
        shutil.copyfile(data / kind / f"{ids(dataset)[0]}.png", data / kind / f"{extra}.png")
    pairs = load_generated_pairs(data)
    assert [p.id for p in pairs] == sorted(ids(dataset)) and extra not in {p.id for p in pairs}
    # segment's fine-noise level of the set (what inference matches): the median over its synthetic images only
    from drgan.segment import TrainingPairs
    from drgan.segmenters.noise_match import noise_level

    synthetic = [read(data / "images" / f"{i}.png") / 255.0 for i in ids(dataset) if i.startswith("syn_")]
    level = TrainingPairs(data=str(data)).noise_level(pairs)
    assert level == pytest.approx(np.median([noise_level(x) for x in synthetic]))
    target = export(data, tmp_path / "raw")
    assert not (target / "labelsTr" / f"{extra}.png").exists()

    (data / "manifest.json").unlink()  # an unfinished generate folder (config.json, no manifest)
    with pytest.raises(DataError, match=rf"^data={data}: a drgan.generate folder without manifest.json"):
        load_generated_pairs(data)
    with pytest.raises(DataError, match=rf"^data={data}: a drgan.generate folder without manifest.json"):
        export(data, tmp_path / "raw2")
    foreign = tmp_path / "foreign"
    (foreign / "images").mkdir(parents=True)
    with pytest.raises(DataError, match=rf"^data={foreign}: not a drgan dataset: no manifest.json \(holds images/"):
        export(foreign, tmp_path / "raw3")


# --- a generator trained with the real background texture -----------------------------------------------------


def test_textured_generator_takes_its_texture_from_the_run_patches(tmp_path, monkeypatch):
    import shutil

    from drgan.models.generator import Generator

    images = make_images(tmp_path / "real" / "images")
    run = tmp_path / "run"
    run_train(
        tiny_overrides(
            images,
            run,
            extra=["trainer.max_epochs=1", "trainer.limit_train_batches=1", "material.background_texture.enabled=true"],
        )
    )
    seen = []
    original = Generator.set_background
    monkeypatch.setattr(
        Generator, "set_background", lambda self, texture: (seen.append(texture), original(self, texture))[1]
    )
    out = tmp_path / "data"
    run_generate(run, out, n=1)
    assert len(seen) == 1 and len(seen[0]) == N_BG  # the run's own background patches
    assert len(ids(out)) == 1 + N_BG

    lonely = tmp_path / "elsewhere" / "best.ckpt"  # a checkpoint without its run folder
    lonely.parent.mkdir()
    shutil.copyfile(run / "checkpoints" / "best.ckpt", lonely)
    with pytest.raises(ConfigError, match="trained with material.background_texture.*give backgrounds=PATCHSET_FOLDER"):
        gen.generate(
            compose(
                [f"ckpt={lonely}", f"out={tmp_path / 'data2'}", "n=1", "n_background=0", "progress=false"],
                config_name="generate",
            )
        )


# --- scene values other than the trained network's (the ablations) -----------------------------------------


def learned_limits(ckpt) -> dict[str, tuple[float, float]]:
    module = gen.load_module(*_module_args(ckpt))
    return {p.key: (p.low, p.high) for p in module.generator.learned}


def _module_args(run):
    from drgan.synthetic.source import checkpoint_config, generator_checkpoint

    ckpt_file, _ = generator_checkpoint(run)
    return ckpt_file, checkpoint_config(ckpt_file)


def test_parameters_middle_and_a_mapping_fix_every_images_values(tiny_run, tmp_path):
    limits = learned_limits(tiny_run)
    out = tmp_path / "middle"
    run_generate(tiny_run, out, "parameters=middle", "n_background=0")
    assert json.loads((out / "config.json").read_text())["fixed"]["parameters"] == "middle"
    with pytest.raises(ConfigError, match="parameters: 'middle' there, None now"):  # never completed with others
        run_generate(tiny_run, out, "n_background=0")
    for meta in sorted((out / "meta").glob("syn_*.json")):
        values = json.loads(meta.read_text())["parameters"]
        for key, (low, high) in limits.items():
            assert values[key] == pytest.approx((low + high) / 2, rel=1e-6)
    chosen = {key: low + 0.25 * (high - low) for key, (low, high) in limits.items()}
    nested: dict = {}
    for key, value in chosen.items():  # YAML nesting: {particle: {roughness: ...}, noise: {sigma: ...}}
        group, name = key.split(".", 1)
        nested.setdefault(group, {})[name] = value
    out = tmp_path / "mapping"
    override = (
        "parameters={"
        + ",".join(f"{g}:{{" + ",".join(f"{k}:{v}" for k, v in d.items()) + "}" for g, d in nested.items())
        + "}"
    )
    run_generate(tiny_run, out, override, "n_background=0")
    for meta in sorted((out / "meta").glob("syn_*.json")):
        values = json.loads(meta.read_text())["parameters"]
        assert all(values[k] == pytest.approx(v, rel=1e-6) for k, v in chosen.items())


def test_parameters_initial_gives_the_network_its_weights_before_training(tiny_run):
    from drgan.models.gan_module import GANModule
    from drgan.synthetic.source import use_parameters

    ckpt_file, cfg = _module_args(tiny_run)
    module = gen.load_module(ckpt_file, cfg)
    trained = {k: v.clone() for k, v in module.generator.regressor.state_dict().items()}
    initial = GANModule.from_config(
        cfg
    ).generator.regressor.state_dict()  # what training started from (same seed, config)
    assert any(not torch.equal(trained[k], initial[k]) for k in trained)  # the one training step moved it
    use_parameters(module, "initial", cfg)
    assert all(torch.equal(v, initial[k]) for k, v in module.generator.regressor.state_dict().items())


def test_bad_parameters_are_refused_naming_what_is_expected(tiny_run, tmp_path):
    from drgan.synthetic.source import use_parameters

    limits = learned_limits(tiny_run)
    with pytest.raises(ConfigError, match="parameters='best'.*trained, initial, middle"):
        run_generate(tiny_run, tmp_path / "a", "parameters=best")
    ckpt_file, cfg = _module_args(tiny_run)
    module = gen.load_module(ckpt_file, cfg)
    first, *rest = limits
    with pytest.raises(ConfigError, match=rf"missing \['{rest[0]}'"):
        use_parameters(module, {first: limits[first][0]}, cfg)
    too_high = {key: high * 2 + 1 for key, (low, high) in limits.items()}
    with pytest.raises(ConfigError, match="not in"):
        use_parameters(module, too_high, cfg)
    assert not (tmp_path / "a").exists()


# --- grey_spread --------------------------------------------------------------------------------------------


def test_match_grey_moves_both_levels_exactly_and_keeps_labels_meaning():
    from drgan.synthetic.grey_spread import draw, match_grey

    labels = np.zeros((8, 8), np.int32)
    labels[2:5, 2:5] = 1
    image = np.where(labels > 0, 0.8, 0.5).astype(np.float32)
    image[0, 0], image[7, 7] = 0.45, 0.55  # background noise: median still 0.5
    moved = match_grey(image, labels, (0.3, 0.9), margin=0)
    assert np.median(moved[labels == 0]) == pytest.approx(0.3, abs=1e-6)
    assert np.median(moved[labels > 0]) == pytest.approx(0.9, abs=1e-6)
    assert moved[0, 0] == pytest.approx(0.3 - 0.05 * 2, abs=1e-6)  # deviations scaled by the contrast gain (2x)
    dark = match_grey(image, labels, (0.8, 0.1), margin=0)  # the direction may flip: the caller draws from its polarity
    assert np.median(dark[labels > 0]) == pytest.approx(0.1, abs=1e-6)
    assert np.array_equal(match_grey(image, np.zeros_like(labels), (0.3, 0.9)), image)  # no particle: unchanged
    levels = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]])
    assert draw(levels, 7) == draw(levels, 7) and {draw(levels, s) for s in range(40)} == {tuple(r) for r in levels}


def test_grey_levels_leave_edges_out_on_both_sides():
    from drgan.synthetic.grey_spread import grey_levels, match_grey

    # A 10 x 10 particle of grey 0.8 with a 2-px bright rim (1.0, SEM edge brightening) and a 2-px halo (0.3) on a
    # 0.1 background: the levels are those of the core and of the far background, whatever the rim and halo.
    image = np.full((40, 40), 0.1, np.float32)
    image[13:27, 13:27] = 0.3  # halo
    image[15:25, 15:25] = 1.0  # rim
    image[17:23, 17:23] = 0.8  # core
    particle = np.zeros((40, 40), bool)
    particle[15:25, 15:25] = True
    assert grey_levels(image, particle) == pytest.approx((0.1, 0.8))
    assert grey_levels(image, particle, margin=0)[1] == pytest.approx(1.0)  # the rim outnumbers the core: 64 vs 36 px
    # an outline found 1 px too small (a classical threshold's) gives the levels of the true one with a wider margin
    smaller = np.zeros_like(particle)
    smaller[16:24, 16:24] = True
    assert grey_levels(image, smaller, margin=3) == pytest.approx((0.1, 0.8))
    moved = match_grey(image, particle, (0.2, 0.6))
    assert grey_levels(moved, particle) == pytest.approx((0.2, 0.6), abs=1e-6)
    # a particle thinner than twice the margin keeps all its pixels
    thin = np.zeros_like(particle)
    thin[5, 5:30] = True
    assert grey_levels(image, thin)[1] == pytest.approx(float(np.median(image[thin])))


def _ramped_discs(background: float, core: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(image, labels) of 4 discs of radius 9 px on 96 x 96 px: grey ``core`` within 4 px of the centre, falling
    linearly to ``background`` at the true outline (a dim edge, as SEM particles' sides), with a little noise."""
    yy, xx = np.mgrid[:96, :96]
    image = np.full((96, 96), background, np.float64)
    labels = np.zeros((96, 96), np.int32)
    for k, (y, x) in enumerate([(24, 24), (24, 70), (70, 26), (68, 68)], 1):
        r = np.hypot(yy - y, xx - x)
        inside = r < 9
        labels[inside] = k
        ramp = np.clip((9 - r) / 5, 0, 1)
        image[inside] = background + (core - background) * ramp[inside]
    image += np.random.default_rng(seed).normal(0, 0.01, image.shape)
    return image.astype(np.float32), labels


def test_grey_spread_measures_generated_images_as_it_measured_the_real_ones():
    from drgan.data.classical import particle_foreground
    from drgan.synthetic.grey_spread import GreySpread, grey_levels, match_grey

    # The classical outline (an Otsu threshold) of a particle with a dim edge lies inside the true one, so the
    # real patches' particle grey is that of the bright part. A generated image of the same particles, moved to
    # that level, must come out with the real image's grey levels on its *true* outlines too.
    segment = {"scale": 18}
    real, real_labels = _ramped_discs(0.1, 0.6, seed=0)
    spread = GreySpread.from_patches(real[None], segment, "bright", resolution=96)
    assert spread.segment.is_resolved  # resolved once on the real patches, not per generated image
    # levels are cores inside the threshold's own outline: grown to the edges it would take in the dim ramp
    assert not spread.segment.grow_outlines
    core = grey_levels(real, particle_foreground(real, spread.segment, "bright"))
    assert spread.levels[0] == pytest.approx(core, abs=1e-6)
    generated, labels = _ramped_discs(0.4, 0.9, seed=1)  # the same particles, other levels
    moved, info = spread.apply(generated, labels, seed=3)
    assert info["measured_by"] == "classical" and info["target"] == pytest.approx(spread.levels[0], abs=1e-4)
    truth = grey_levels(real, real_labels > 0)
    assert grey_levels(moved, labels > 0) == pytest.approx(truth, abs=0.01)
    # measured by its labels instead, the generated image's particles come out brighter than the real ones
    by_labels = match_grey(generated, labels, tuple(spread.levels[0]))
    assert grey_levels(by_labels, labels > 0)[1] > truth[1] + 0.03
    # an image in which the segmentation finds no particle is measured by its labels
    flat = (0.4 + np.random.default_rng(2).normal(0, 0.01, (96, 96))).astype(np.float32)
    assert spread.particles(flat, labels)[1] == "labels"


def test_grey_spread_gives_each_image_a_real_patchs_grey_levels(tiny_run, tmp_path):
    from drgan.data.patches import PatchSet
    from drgan.synthetic.grey_spread import GreySpread, grey_levels

    patches = PatchSet.load(tiny_run / "patches")
    out = tmp_path / "spread"
    run_generate(tiny_run, out, "grey_spread=true", n_background=0)
    resolution = read(out / "images" / f"{ids(out)[0]}.png").shape[0]
    spread = GreySpread.from_patches(patches.train, patches.params["segment"], patches.params["polarity"], resolution)
    for item in ids(out):
        image = read(out / "images" / f"{item}.png").astype(np.float64) / 255
        labels = read(out / "labels" / f"{item}.png")
        meta = json.loads((out / "meta" / f"{item}.json").read_text())["grey_spread"]
        assert meta["measured_by"] in ("classical", "labels")
        assert any(np.allclose(meta["target"], level, atol=1e-4) for level in spread.levels)  # one real patch's
        # measured as it was moved: the background grey of that patch (to 8-bit rounding; the particle grey is exact
        # before clipping to [0, 1], which moves it on these tiny, noisy 24 px renders)
        if meta["measured_by"] == "labels":
            particle = labels > 0
        else:
            particle = spread.particles(image.astype(np.float32), labels)[0]
        assert grey_levels(image, particle)[0] == pytest.approx(meta["target"][0], abs=0.01)
    assert json.loads((out / "config.json").read_text())["fixed"]["grey_spread"] is True
    with pytest.raises(ConfigError, match="grey_spread"):  # a folder keeps its settings: resuming without it is refused
        run_generate(tiny_run, out, "grey_spread=false", n_background=0)
    run_generate(tiny_run, out, n_background=0)  # the default (auto) is on where the run has its real patches
