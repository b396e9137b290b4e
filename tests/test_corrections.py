"""The correction loop: a user's corrected outlines (napari label TIFFs, Fiji ROI sets, masks) read back as particles,
turned into training pairs at the segmenter's scale, and a segmenter fine-tuned on them (drgan.segmenters.corrections,
``drgan segment finetune=RUN corrected=DIR``, the pipeline's finetune stage)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from omegaconf import OmegaConf
from PIL import Image

from drgan.core.errors import ConfigError, DataError
from drgan.data.imagej import write_label_tiff, write_roi_set
from drgan.launch.configs import compose
from drgan.segmenters.corrections import (
    correction_pairs,
    crops_for_share,
    find_corrections,
    load_corrections,
    rois_to_labels,
)

sys.path.insert(0, str(Path(__file__).parent))
from test_segment import disc_image, disc_labels, make_generated  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def same_particles(a: np.ndarray, b: np.ndarray) -> bool:
    """The same particles whatever their ids: every id of one covers exactly the pixels of one id of the other."""
    pairs = {(int(x), int(y)) for x, y in zip(a.ravel(), b.ravel())}
    return len(pairs) == len({x for x, _ in pairs}) == len({y for _, y in pairs})


def write_image(folder: Path, image_id: str, image: np.ndarray) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(folder / f"{image_id}.tif", (np.asarray(image) * 255).astype(np.uint8))
    return folder


def test_outlines_saved_by_napari_fiji_or_as_masks_give_the_same_particles(tmp_path):
    labels = {k: disc_labels(48, n=5, seed=s) for k, s in (("a", 1), ("b", 2), ("c", 3))}
    images = tmp_path / "images"
    for k, lab in labels.items():
        write_image(images, k, disc_image(lab))
    fixes = tmp_path / "fixes"
    write_label_tiff(fixes / "labels" / "a.tif", labels["a"] * 7)  # napari keeps whatever ids the user painted
    write_roi_set(fixes / "rois" / "b.zip", labels["b"])  # Fiji's ROI Manager, saved
    (fixes / "masks").mkdir()
    Image.fromarray(((labels["c"] > 0) * 255).astype(np.uint8)).save(fixes / "masks" / "c.png")  # a binary mask
    assert set(find_corrections(fixes)) == {"a", "b", "c"}
    read = {item.id: lab for item, lab in load_corrections(fixes, images, crop_rows=None)}
    assert set(read) == {"a", "b", "c"}
    from drgan.segmenters.pairs import instance_labels

    labels["c"] = instance_labels(labels["c"] > 0)  # a binary mask's particles: its 4-connected components
    for k, lab in labels.items():
        assert read[k].shape == lab.shape and same_particles(read[k], lab), k
        assert read[k].max() == lab.max()  # renumbered 1..N


def test_overlapping_rois_give_the_later_one_the_shared_pixels():
    first = np.zeros((6, 6), bool)
    first[1:4, 1:4] = True
    second = np.zeros((6, 6), bool)
    second[2:5, 2:5] = True
    labels = rois_to_labels([first, np.zeros((6, 6), bool), second], (6, 6))
    assert labels.max() == 2 and labels[2, 2] == 2 and labels[1, 1] == 1 and (labels == 1).sum() == 9 - 4


@pytest.mark.parametrize(
    "case, error, message",
    [
        ("empty", DataError, "holds no corrected outlines"),
        ("twice", DataError, "has 2 outline files"),
        ("unknown id", DataError, "no image for 1 requested id"),
        ("other size", DataError, "expected the outline drawn on that image"),
        ("no particle", DataError, "holds no particle"),
        ("no images", ConfigError, "give correction.images=FOLDER"),
    ],
)
def test_bad_corrections_are_named_before_anything_trains(case, error, message, tmp_path):
    lab = disc_labels(32, seed=0)
    images = write_image(tmp_path / "images", "a", disc_image(lab))
    fixes = tmp_path / "fixes"
    fixes.mkdir()
    outline = {"unknown id": "zz", "other size": "a", "no particle": "a"}.get(case, "a")
    if case != "empty":
        shape_lab = np.zeros((20, 20), np.int32) if case == "other size" else lab
        write_label_tiff(fixes / f"{outline}.tif", np.zeros_like(lab) if case == "no particle" else shape_lab)
    if case == "twice":
        write_roi_set(fixes / "a.zip", lab)
    with pytest.raises(error, match=message):
        load_corrections(fixes, None if case == "no images" else images, crop_rows=None)


def test_corrected_pairs_are_what_inference_shows_the_segmenter(tmp_path):
    """Resampled by the segmenter's pixel scale as inference resamples images, the labels by nearest neighbour and
    their classes drawn anew; noise added up to the generated images' level."""
    from drgan.data.images import resample
    from drgan.scene.labels import CONTOUR, PARTICLE
    from drgan.segmenters.noise_match import noise_level

    lab = disc_labels(64, n=4, radius=8.0, seed=5)
    images = write_image(tmp_path / "images", "a", disc_image(lab))
    write_label_tiff(tmp_path / "fixes" / "a.tif", lab)
    items = load_corrections(tmp_path / "fixes", images, crop_rows=None)
    (pair,) = correction_pairs(items, 0.5, 1)
    assert pair.image.shape == pair.mask.shape == pair.labels.shape == (32, 32)
    np.testing.assert_allclose(pair.image, resample(items[0][0].image, 0.5), atol=1e-6)
    assert pair.labels.max() == lab.max() and set(np.unique(pair.mask)) == {0, PARTICLE, CONTOUR}
    noisy = correction_pairs(items, 1.0, 1, noise=0.2)[0]
    assert noise_level(noisy.image) > noise_level(items[0][0].image) + 0.05
    counts = crops_for_share([pair, pair], 30, 0.75)
    assert sum(counts) == 90 and counts[0] == counts[1]  # 3 corrected crops for each generated one
    with pytest.raises(ConfigError, match="correction.share=1.0"):
        crops_for_share([pair], 30, 1.0)


def exact_generated(folder: Path, n: int) -> Path:
    """make_generated's bright discs with their exact instance labels (labels/), as drgan.generate writes them."""
    make_generated(folder, n=n)
    (folder / "labels").mkdir()
    for i in range(n):
        Image.fromarray(disc_labels(32, seed=i).astype(np.uint8)).save(folder / "labels" / f"{i:03d}.png")
    return folder


def test_fine_tuning_on_one_corrected_image_teaches_what_the_generated_pairs_did_not(tmp_path):
    """A segmenter of bright particles finds nothing on an image of dark ones; fine-tuned on one such image with its
    outlines corrected, it finds the dark particles of another image. Its generated pairs, validation split and
    closed-loop check are its base run's; its checkpoint keeps the base's scale and records what it learnt from."""
    from drgan.segment import segment
    from drgan.segmenters.inference import predict
    from drgan.segmenters.registry import load_segmenter

    data = exact_generated(tmp_path / "gen", 16)
    base = tmp_path / "base"
    tiny = ["loader.crop=32", "loader.batch_size=4", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false",
            "logger=none", f"paths.root_dir={tmp_path}"]  # fmt: skip
    cfg = compose([f"data={data}", f"out={base}", "model.depth=2", "model.base=4", "model.lr=1e-2",
                   "trainer.max_epochs=4", "check_fraction=0.25", "seed=3", *tiny], config_name="segment")  # fmt: skip
    segment(cfg)
    (base / ".hydra").mkdir()
    OmegaConf.save(cfg, base / ".hydra" / "config.yaml")  # as Hydra writes it beside every segment run

    dark = {k: disc_labels(64, n=6, seed=s) for k, s in (("fixed", 3), ("new", 9))}
    images = tmp_path / "images"
    for k, lab in dark.items():
        write_image(images, k, 1.0 - disc_image(lab, seed=len(k)))
    write_label_tiff(tmp_path / "fixes" / "fixed.tif", dark["fixed"])

    def dsc(checkpoint, image_id="new"):
        image = tifffile.imread(images / f"{image_id}.tif").astype(np.float32) / 255
        found = predict(load_segmenter(checkpoint), image, split="none", tile=32) > 0
        truth = dark[image_id] > 0
        return 2 * (found & truth).sum() / (found.sum() + truth.sum())

    assert dsc(base / "checkpoints" / "last.ckpt") < 0.3
    tuned = tmp_path / "tuned"
    segment(compose([f"finetune={base}", f"corrected={tmp_path / 'fixes'}", f"correction.images={images}",
                     f"out={tuned}", "correction.epochs=8", "correction.lr=1e-2", "correction.share=0.8", "seed=0",
                     "crop_rows=null", *tiny], config_name="segment"))  # fmt: skip
    assert dsc(tuned / "checkpoints" / "last.ckpt") > 0.8
    metrics = json.loads((tuned / "metrics.json").read_text())
    before = json.loads((base / "metrics.json").read_text())
    assert metrics["finetuned"]["images"] == ["fixed"] and metrics["finetuned"]["particles"] == 6
    assert metrics["closed_loop"]["ids"] == before["closed_loop"]["ids"]  # the base's held-out pairs, never trained on
    assert metrics["pixel_scale"] == before["pixel_scale"]
    model = load_segmenter(tuned / "checkpoints" / "last.ckpt")
    assert model.hparams.depth == 2 and model.hparams.lr == pytest.approx(1e-2)  # the base's network
    assert metrics["split_calibration"]["n_pairs"] >= 2  # the corrected image and the validation pairs


def test_fine_tuning_needs_both_settings_and_a_checkpoint(tmp_path):
    from drgan.segment import segment

    with pytest.raises(ConfigError, match="needs both finetune=RUN"):
        segment(compose([f"finetune={tmp_path}", f"out={tmp_path / 'o'}"], config_name="segment"))
    (tmp_path / "fixes").mkdir()
    with pytest.raises(DataError, match="no segmenter checkpoint there"):
        segment(compose([f"finetune={tmp_path}", f"corrected={tmp_path / 'fixes'}", f"out={tmp_path / 'o'}"],
                        config_name="segment"))  # fmt: skip
    assert not (tmp_path / "o").exists()


def test_the_pipeline_refuses_a_corrected_image_it_would_score(tmp_path):
    from drgan import pipeline
    from drgan.pipeline import stages

    lab = disc_labels(32, seed=1)
    data = write_image(tmp_path / "data", "a", disc_image(lab))
    write_image(data, "b", disc_image(disc_labels(32, seed=2)))
    (data / "split.json").write_text(json.dumps({"train": ["b"], "test": ["a"]}))  # a is scored, never trains
    annotated = write_image(tmp_path / "ann" / "images", "a", disc_image(lab)).parent
    (annotated / "masks").mkdir()
    write_label_tiff(tmp_path / "fixes" / "a.tif", lab)
    words = [f"data.dir={data}", "name=t", f"out={tmp_path / 'o'}", f"corrected={tmp_path / 'fixes'}"]
    with pytest.raises(DataError, match="corrected image.*scored at the end too"):
        stages.check_inputs(pipeline.parse_settings([*words, f"annotated={annotated}"]))
    assert stages.check_inputs(pipeline.parse_settings(words))["corrected_images"] == 1
