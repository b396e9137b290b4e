"""drgan.synthetic: the folder of a synthetic dataset, written and read without a renderer (hand-made arrays).

The render loop that fills it (drgan.generate) is tested in tests/test_generate.py and tests/test_faults_generate.py.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from drgan.core import io
from drgan.core.errors import ConfigError, DataError
from drgan.synthetic import manifest as mf
from drgan.synthetic.folder import DatasetFolder, bg_id, syn_id, syn_index
from drgan.synthetic.generation_settings import FIXED_SETTINGS, GenerateSettings
from drgan.synthetic.shards import Shard, owned_by

SIZE = 12


def settings(n: int, n_background: int = 1, **more) -> GenerateSettings:
    """Settings as GenerateSettings.resolve gives them (no checkpoint needed here)."""
    given = {
        "ckpt": "/runs/x/checkpoints/best.ckpt", "grey_spread": False, "material": "tio2_sem", "n": n,
        "n_background": n_background, "seed": 0, "contour_px": 1, "min_contrast": 0.0, "min_background": 0.05,
        "polarity": "bright", "renderer": {"spp": 1, "resolution": SIZE}, "backgrounds": None, "out": "unused",
    }  # fmt: skip
    return GenerateSettings(**{**given, **more})


def item_arrays(index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A deterministic (image in [0, 1], 3-class mask, instance labels) for an index: one square particle."""
    labels = np.zeros((SIZE, SIZE), np.int32)
    y = index % (SIZE - 4)
    labels[y : y + 4, 2:6] = 1
    mask = (labels > 0).astype(np.uint8)
    mask[y, 2:6] = 2
    image = np.where(labels > 0, 0.8, 0.1 + 0.01 * index).astype(np.float32)
    return image, mask, labels


def write_synthetic(folder: DatasetFolder, index: int, kept: bool = True) -> None:
    if kept:
        image, mask, labels = item_arrays(index)
        folder.write(syn_id(index), image, mask, labels, {"kind": "synthetic", "index": index})
    else:
        folder.write_dropped(syn_id(index), {"reason": "contrast", "kind": "synthetic", "index": index})


def write_background(folder: DatasetFolder, k: int) -> None:
    zeros = np.zeros((SIZE, SIZE), np.uint8)
    folder.write(bg_id(k), np.full((SIZE, SIZE), 0.2, np.float32), zeros, zeros, {"kind": "background", "index": k})


def read_png(path: Path) -> np.ndarray:
    with Image.open(path) as image:
        return np.asarray(image)


def test_ids_and_files():
    assert syn_id(12) == "syn_000012" and bg_id(3) == "bg_0003"
    assert syn_index("syn_000012") == 12 and syn_index("bg_0003") is None and syn_index("syn_x") is None
    assert mf.Entry.synthetic(5).to_json() == {
        "id": "syn_000005", "kind": "synthetic", "index": 5,
        "files": {"image": "images/syn_000005.png", "mask": "masks/syn_000005.png",
                  "label": "labels/syn_000005.png", "meta": "meta/syn_000005.json"},
    }  # fmt: skip
    assert list(mf.Entry.background("bg_0000").to_json()) == ["id", "kind", "files"]


def test_write_read_roundtrip(tmp_path):
    """Items written by DatasetFolder come back from the manifest, pixel for pixel, in id order."""
    from drgan.segmenters.pairs import load_generated_pairs

    folder = DatasetFolder(tmp_path / "data")
    folder.check_settings(settings(3).fixed())
    for index, kept in ((0, True), (1, False), (2, True), (3, True)):
        write_synthetic(folder, index, kept)
    write_background(folder, 0)
    assert folder.outcomes() == {0: True, 1: False, 2: True, 3: True}
    facts = {"name": "tio2_sem", "clark_evans": 0.54}
    written = mf.write_manifest(folder, settings(3), stats={"rendered": 4}, required=True, material=facts)

    manifest = mf.read_manifest(folder.root)
    assert manifest["material"] == facts
    assert manifest == written == json.loads((folder.root / "manifest.json").read_text())
    assert "model_cfg" not in manifest["config"] and manifest["config"]["shard"] is None
    assert manifest["counts"] == {
        "synthetic": 3,
        "background": 1,
        "partial_background": 0,
        "kept": 3,
        "dropped": 1,
        "drop_reasons": {"contrast": 1},
        "attempted": 4,
        "surplus_kept_not_listed": 0,
    }
    entries = mf.manifest_entries(manifest)
    assert [e.id for e in entries] == ["syn_000000", "syn_000002", "syn_000003", "bg_0000"]
    assert [e.index for e in entries] == [0, 2, 3, None]
    for entry in entries[:3]:
        image, mask, labels = item_arrays(entry.index)
        np.testing.assert_array_equal(read_png(folder.root / entry.files["mask"]), mask)
        np.testing.assert_array_equal(read_png(folder.root / entry.files["label"]), labels)
        grey = np.round(image * 255).astype(np.uint8)
        np.testing.assert_array_equal(read_png(folder.root / entry.files["image"]), grey)
        meta = json.loads((folder.root / entry.files["meta"]).read_text())
        assert meta["id"] == entry.id and meta["files"] == entry.files

    pairs = load_generated_pairs(folder.root)
    assert [p.id for p in pairs] == ["bg_0000", "syn_000000", "syn_000002", "syn_000003"]  # sorted by id
    np.testing.assert_array_equal(pairs[1].mask, item_arrays(0)[1])
    assert pairs[1].image.dtype == np.float32 and pairs[1].image.max() == pytest.approx(0.8, abs=1 / 255)
    assert not [p for p in folder.root.rglob("*") if ".tmp" in p.name]  # every write atomic


def test_other_settings_are_refused_and_n_may_grow(tmp_path):
    folder = DatasetFolder(tmp_path / "data")
    folder.check_settings(settings(3).fixed())
    assert list(json.loads((folder.root / "config.json").read_text())["fixed"]) == list(FIXED_SETTINGS)
    folder.check_settings(settings(30, n_background=5).fixed())  # n, n_background: not fixed
    with pytest.raises(ConfigError, match=r"generated with other settings \(seed: 0 there, 7 now\)"):
        folder.check_settings(replace(settings(3), seed=7).fixed())


def test_resume_of_a_half_written_shard(tmp_path):
    """Shard 1/2 killed mid-item: its leftovers go, shard 0's do not; the dataset is complete only when
    the missing index is done, and then lists the first n kept indices whoever rendered them."""
    folder = DatasetFolder(tmp_path / "data")
    s = settings(4, n_background=0)
    for index in (0, 2, 4):  # shard 0 is done with its part
        write_synthetic(folder, index)
    write_synthetic(folder, 1)
    # Shard 1 was killed in index 3: image and mask written, labels in flight, no meta record.
    image, mask, _ = item_arrays(3)
    io.write_png(folder.root / "images" / "syn_000003.png", image)
    io.write_png(folder.root / "masks" / "syn_000003.png", mask)
    in_flight = folder.root / "labels" / ".syn_000003.png.k1ll3d.tmp.png"
    in_flight.write_bytes(b"\x89PNG half")
    other = folder.root / "images" / ".syn_000006.png.r4nn1ng.tmp.png"  # shard 0's write, still running
    other.write_bytes(b"\x89PNG")
    shard = Shard.parse("1/2")
    assert not folder.done(syn_id(3)) and 3 not in folder.outcomes()

    # Shard 0 finishing meanwhile cannot write the manifest yet; merge=true says which index is missing.
    assert mf.write_manifest(folder, s, stats=None, required=False) is None
    with pytest.raises(ConfigError, match=r"index 3 \(syn_000003\) is not done yet \(3 of n=4 kept below it\)"):
        mf.write_manifest(folder, s, stats=None, required=True)

    removed = folder.remove_partial(lambda item: owned_by(item, shard))
    assert removed == {"temporary": 1, "unpaired": 2}
    assert not in_flight.exists() and other.exists()
    assert not (folder.root / "images" / "syn_000003.png").exists()
    assert (folder.root / "images" / "syn_000002.png").exists()

    write_synthetic(folder, 3)  # the resumed shard renders the index again
    mf.write_shard_manifest(folder, s, shard, {"rendered": 1})
    shard_record = json.loads((folder.root / "manifest_shard_1.json").read_text())
    assert [e["id"] for e in shard_record["entries"]] == ["syn_000001", "syn_000003"]
    manifest = mf.write_manifest(folder, s, stats={"rendered": 1}, required=False)
    assert [e["id"] for e in manifest["entries"]] == [syn_id(i) for i in range(4)]
    assert manifest["counts"]["surplus_kept_not_listed"] == 1  # index 4, kept by shard 0 beyond the 4th
    assert manifest["throughput"]["shards"] == [{"shard": "1/2", "rendered": 1}]
    # A reader takes the manifest's items, not every image on disk.
    assert [item for item, _, _ in mf.image_mask_pairs(folder.root)] == [syn_id(i) for i in range(4)]
    assert mf.unlisted_items(folder.root, mf.manifest_entries(manifest)) == ["syn_000004"]


def test_foreign_and_unfinished_folders_are_named(tmp_path):
    from drgan.segmenters.pairs import load_generated_pairs

    real = tmp_path / "tio2_like"  # a real dataset: images and split, binary masks under another name
    (real / "images").mkdir(parents=True)
    (real / "split.json").write_text("{}")
    with pytest.raises(DataError, match=rf"^data={real}: not a drgan dataset: no manifest.json.*holds images/, split"):
        load_generated_pairs(real)
    with pytest.raises(DataError, match=rf"^data={real}: not a drgan dataset: no manifest.json"):
        mf.read_manifest(real)
    with pytest.raises(DataError, match=rf"^data={tmp_path / 'nowhere'}: no such folder \(expected a dataset folder"):
        load_generated_pairs(tmp_path / "nowhere")

    unfinished = DatasetFolder(tmp_path / "unfinished")  # generate started there, no manifest yet
    unfinished.check_settings(settings(2).fixed())
    write_synthetic(unfinished, 0)
    with pytest.raises(DataError, match=r"without manifest.json, so the dataset is not complete.*merge=true"):
        load_generated_pairs(unfinished.root)

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "manifest.json").write_text('{"entries": [')
    with pytest.raises(DataError, match=rf"^data={broken}: manifest.json cannot be read"):
        mf.read_manifest(broken)
    (broken / "manifest.json").write_text(json.dumps({"entries": [{"id": "a", "kind": "synthetic", "files": {}}]}))
    with pytest.raises(DataError, match=r"entry 0 .* is not an item with 'id' and 'files' holding 'image' and 'mask'"):
        mf.read_manifest(broken)
    outside = {"id": "a", "kind": "synthetic", "files": {"image": "../../etc/a.png", "mask": "masks/a.png"}}
    (broken / "manifest.json").write_text(json.dumps({"entries": [outside]}))
    with pytest.raises(DataError, match=r"entry a names '../../etc/a.png' \(expected a path inside the dataset folder"):
        mf.read_manifest(broken)
    (broken / "manifest.json").write_text(json.dumps({"entries": []}))
    with pytest.raises(DataError, match="manifest.json lists no entries"):
        mf.read_manifest(broken)


def test_missing_file_of_a_listed_item_is_named(tmp_path):
    folder = DatasetFolder(tmp_path / "data")
    write_synthetic(folder, 0)
    mf.write_manifest(folder, settings(1, n_background=0), stats=None, required=True)
    (folder.root / "masks" / "syn_000000.png").unlink()
    with pytest.raises(DataError, match=r"masks/syn_000000.png of syn_000000 is missing"):
        mf.image_mask_pairs(folder.root)


def test_hand_made_pairs_without_manifest_are_paired_by_name(tmp_path):
    root = tmp_path / "pairs"
    for name in ("b", "a"):
        image, mask, _ = item_arrays(1)
        io.write_png(root / "images" / f"{name}.png", image)
        io.write_png(root / "masks" / f"{name}.png", mask)
    pairs = [(i, p.name, m.name) for i, p, m in mf.image_mask_pairs(root)]
    assert pairs == [("a", "a.png", "a.png"), ("b", "b.png", "b.png")]
    (root / "masks" / "b.png").unlink()
    with pytest.raises(DataError, match=rf"data={root}: no mask for 1 image\(s\) in masks/, e.g. 'b'"):
        mf.image_mask_pairs(root)


# --- partial backgrounds and the ignore value ----------------------------------------------------------------

PATCH = 32
# Training patches (seeded discs of radius 4.5 px): 0, 1 and 3 are usable; 2 is so full that particles and their
# margin cover most of it (skipped: ignored fraction > 0.6); 4 shows no particle at all (skipped: nothing found).
TRAIN_DISCS = [
    [(8, 8)],
    [(8, 8), (20, 22)],
    [(6, 6), (6, 18), (6, 28), (16, 12), (18, 26), (27, 6), (27, 18), (28, 28)],
    [(16, 15)],
    [],
]


def disc_patch(centres, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(bright discs on a dark noisy background, float32; the discs' pixels, bool)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:PATCH, :PATCH]
    disc = np.zeros((PATCH, PATCH), bool)
    for cy, cx in centres:
        disc |= (yy - cy) ** 2 + (xx - cx) ** 2 <= 4.5**2
    image = 0.15 + 0.02 * rng.standard_normal((PATCH, PATCH))
    image[disc] = 0.8
    return image.astype(np.float32), disc


def partial_patchset(root: Path) -> tuple[Path, list[np.ndarray]]:
    """A PatchSet folder of 32 px patches with one background patch and the TRAIN_DISCS training patches, mined
    (as its params say) with the resolved segmentation of these discs; returns it and the discs of each patch."""
    from drgan.data.classical import SegmentParams
    from drgan.data.patches import PatchSet

    patches, discs = zip(*(disc_patch(c, seed) for seed, c in enumerate(TRAIN_DISCS)))
    background = disc_patch([], 99)[0][None]
    segment = SegmentParams(scale=9, sigma=1.0, min_distance=7, min_area=40, max_area=4000).resolved()
    PatchSet(
        train=np.stack(patches),
        train_ids=[f"img{k}" for k in range(len(patches))],
        train_positions=np.array([(k, 2 * k) for k in range(len(patches))]),
        train_counts=np.array([len(c) for c in TRAIN_DISCS]),
        background=background,
        background_ids=["img9"],
        background_positions=np.array([(0, 0)]),
        params={"size": PATCH, "segment": segment.as_dict(), "polarity": "bright"},
    ).save(root)
    return root, list(discs)


def test_partial_backgrounds_fill_up_n_background_with_their_particles_ignored(tmp_path, caplog):
    from scipy import ndimage

    from drgan.segmenters.pairs import load_generated_pairs
    from drgan.synthetic.backgrounds import PartialSettings, write_backgrounds
    from drgan.synthetic.folder import IGNORE, pbg_id

    path, discs = partial_patchset(tmp_path / "patches")
    s = settings(1, n_background=5, backgrounds=str(path))
    folder = DatasetFolder(tmp_path / "data")
    write_synthetic(folder, 0)
    with caplog.at_level("INFO", logger="drgan.synthetic.backgrounds"):
        counts = write_backgrounds(folder, str(path), 5, PATCH, PartialSettings(), "bright")
    assert counts == {"background": 1, "partial": 3}
    assert "skipped 1 of 5 windows with particles whose ignored fraction exceeds partial_max_ignored=0.6" in caplog.text
    assert "found no particle again (img4 at (4, 8))" in caplog.text
    assert "only 3 of 5 windows with particles are usable" in caplog.text
    assert folder.done(bg_id(0)) and not folder.done(bg_id(1)) and not folder.done(pbg_id(3))

    fractions, sources = [], []
    for j in range(3):
        files = {k: folder.root / v for k, v in folder.files(pbg_id(j)).items()}
        meta = json.loads(files["meta"].read_text())
        mask, labels = read_png(files["mask"]), read_png(files["label"])
        k = meta["source"]["train_index"]
        assert meta["kind"] == "partial_background" and meta["source"]["image_id"] == f"img{k}"
        assert set(np.unique(mask).tolist()) <= {0, IGNORE} and not labels.any()
        assert (mask[discs[k]] == IGNORE).all()  # every particle pixel ignored ...
        far = ndimage.distance_transform_edt(~discs[k]) > meta["margin_px"] + 1.5
        assert (mask[far] == 0).all()  # ... and what lies beyond its margin is background
        assert meta["margin_px"] == 3 and meta["ignored_fraction"] == pytest.approx((mask == IGNORE).mean())
        np.testing.assert_array_equal(read_png(files["image"]), np.round(disc_patch(TRAIN_DISCS[k], k)[0] * 255))
        fractions.append(meta["ignored_fraction"])
        sources.append(k)
    assert sorted(sources) == [0, 1, 3] and fractions == sorted(fractions) and max(fractions) <= 0.6

    manifest = mf.write_manifest(folder, s, stats=None, required=True)  # complete: the PatchSet has no more
    assert manifest["counts"]["background"] == 1 and manifest["counts"]["partial_background"] == 3
    assert [e["kind"] for e in manifest["entries"]] == ["synthetic", "background"] + ["partial_background"] * 3
    summary = manifest["partial_backgrounds"]
    assert summary["skipped"] == {"ignored_fraction": 1, "no_particle_found": 1} and summary["usable"] == 3
    assert summary["ignored_fraction"]["max"] == pytest.approx(max(fractions), abs=1e-4)
    pairs = {p.id: p for p in load_generated_pairs(folder.root)}
    assert IGNORE in pairs[pbg_id(0)].mask and set(np.unique(pairs[bg_id(0)].mask)) == {0}

    # Resumable: an unfinished partial background is written again, the same; a larger n_background asks for more.
    reference = (folder.root / "masks" / f"{pbg_id(1)}.png").read_bytes()
    (folder.root / "meta" / f"{pbg_id(1)}.json").unlink()
    folder.remove_partial(lambda item: owned_by(item, Shard(0, 1)))
    assert mf.write_manifest(folder, s, stats=None, required=False) is None  # pbg_0001 is missing now
    write_backgrounds(folder, str(path), 5, PATCH, PartialSettings(), "bright")
    assert (folder.root / "masks" / f"{pbg_id(1)}.png").read_bytes() == reference
    assert [e["id"] for e in mf.write_manifest(folder, s, stats=None, required=True)["entries"]][-1] == pbg_id(2)


def test_partial_backgrounds_at_a_lower_resolution_and_without_them(tmp_path):
    from drgan.synthetic.backgrounds import PartialSettings, write_backgrounds
    from drgan.synthetic.folder import IGNORE, pbg_id

    path, discs = partial_patchset(tmp_path / "patches")
    folder = DatasetFolder(tmp_path / "half")
    write_backgrounds(folder, str(path), 2, PATCH // 2, PartialSettings(margin_px=0), "bright")
    meta = json.loads((folder.root / "meta" / f"{pbg_id(0)}.json").read_text())
    mask = read_png(folder.root / "masks" / f"{pbg_id(0)}.png")
    assert mask.shape == (PATCH // 2, PATCH // 2) and meta["margin_px"] == 0
    # Resized, a pixel is ignored whenever a particle pixel falls in it: no particle becomes background.
    covered = discs[meta["source"]["train_index"]].reshape(PATCH // 2, 2, PATCH // 2, 2).any(axis=(1, 3))
    assert (mask[covered] == IGNORE).all()

    # partial_background=false: fewer background items, as before partial backgrounds existed.
    s = settings(1, n_background=3, backgrounds=str(path), partial_background=False)
    folder = DatasetFolder(tmp_path / "without")
    write_synthetic(folder, 0)
    assert write_backgrounds(folder, str(path), 3, PATCH, PartialSettings(enabled=False)) == {"background": 1}
    manifest = mf.write_manifest(folder, s, stats=None, required=True)
    assert [e["id"] for e in manifest["entries"]] == ["syn_000000", "bg_0000"]
    assert manifest["counts"]["partial_background"] == 0 and not (folder.root / "partial_backgrounds.json").exists()


def test_partial_settings_are_fixed_only_when_not_the_defaults_and_shard_0_writes_them(tmp_path):
    from drgan.synthetic.backgrounds import patchset_segmentation
    from drgan.synthetic.folder import pbg_id

    folder = DatasetFolder(tmp_path / "data")
    folder.check_settings(settings(3).fixed())  # a folder made before partial backgrounds existed ...
    defaults = {"partial_background": True, "partial_max_ignored": 0.6, "partial_margin_px": None}
    folder.check_settings(settings(3, **defaults).fixed())  # ... resumes with the defaults
    with pytest.raises(ConfigError, match=r"partial_background: None there, False now"):
        folder.check_settings(settings(3, **{**defaults, "partial_background": False}).fixed())
    with pytest.raises(ConfigError, match=r"partial_max_ignored: None there, 0.3 now"):
        folder.check_settings(settings(3, **{**defaults, "partial_max_ignored": 0.3}).fixed())
    assert pbg_id(2) == "pbg_0002" and syn_index("pbg_0002") is None
    assert owned_by("pbg_0002", Shard(0, 2)) and not owned_by("pbg_0002", Shard(1, 2))
    assert owned_by("partial_backgrounds", Shard(0, 2)) and not owned_by("partial_backgrounds", Shard(1, 2))

    # A PatchSet resampled from 64 px windows to 32 px patches: its segmentation lengths are halved.
    class Resampled:
        params = {"segment": {"scale": 18.0, "sigma": 2.0, "min_distance": 8, "min_area": 160, "max_area": 16000,
                              "background": 54.0}, "polarity": "dark", "window": 64, "size": 32}  # fmt: skip
        patch_size = 32

    params, polarity = patchset_segmentation(Resampled, "bright")
    assert polarity == "dark" and (params.scale, params.sigma, params.min_distance) == (9.0, 1.0, 4)
    assert (params.min_area, params.max_area, params.background) == (40, 4000, 27.0)


def test_generated_masks_may_hold_the_ignore_value_but_no_other(tmp_path):
    from drgan.segmenters.pairs import load_generated_pairs

    root = tmp_path / "pairs"
    image, mask, _ = item_arrays(1)
    mask = mask.copy()
    mask[-2:, -2:] = 255
    io.write_png(root / "images" / "a.png", image)
    io.write_png(root / "masks" / "a.png", mask)
    (pair,) = load_generated_pairs(root)
    np.testing.assert_array_equal(pair.mask, mask)
    mask[0, 0] = 7
    io.write_png(root / "masks" / "a.png", mask)
    with pytest.raises(DataError, match=r"mask .*masks/a.png: unexpected values \[7\] .*or 255 ignore"):
        load_generated_pairs(root)


def test_material_facts_carry_the_profiled_arrangement_and_refuse_a_bad_one():
    """The Clark-Evans ratio a profiled material carries reaches the manifest's "material" (drgan.segment's
    contact_weight=auto reads it); a hand-written material has none; a value that is no ratio is refused."""
    from conftest import compose

    material = compose(["material=tio2_sem", "material.clark_evans=0.6"], config_name="train").material
    assert mf.material_facts(material) == {"name": "tio2_sem", "clark_evans": 0.6}
    assert mf.material_facts(compose(["material=tio2_sem"], config_name="train").material)["clark_evans"] is None
    with pytest.raises(ConfigError, match=r"material.clark_evans=-1.0: expected null or a finite number > 0"):
        mf.material_facts(compose(["material=tio2_sem", "material.clark_evans=-1.0"], config_name="train").material)
