"""Segmenter, sliding-window inference, evaluation and particle analysis on tiny synthetic data.

Images are bright discs / squares on a dark background, 32-64 px; trainings run a few steps.
"""

from __future__ import annotations

import csv
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch
from conftest import compose
from PIL import Image

from drgan.core.errors import ConfigError, DataError
from drgan.scene.labels import class_mask

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def disc_labels(size=32, n=3, radius=4.0, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    labels = np.zeros((size, size), np.int32)
    for k in range(n):
        cy, cx = rng.uniform(radius + 2, size - radius - 2, 2)
        labels[((yy - cy) ** 2 + (xx - cx) ** 2 <= radius**2) & (labels == 0)] = k + 1
    return labels


def disc_image(labels, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(np.where(labels > 0, 0.8, 0.2) + 0.03 * rng.standard_normal(labels.shape), 0, 1).astype(np.float32)


def make_generated(folder: Path, n=6, size=32) -> Path:
    for d in ("images", "masks"):
        (folder / d).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        labels = disc_labels(size, seed=i)
        Image.fromarray((disc_image(labels, i) * 255).astype(np.uint8)).save(folder / "images" / f"{i:03d}.png")
        Image.fromarray(class_mask(labels, 1)).save(folder / "masks" / f"{i:03d}.png")
    return folder


def make_real(folder: Path, images: dict, masks: dict, split: dict) -> Path:
    """A real-style dataset: images/ID.tif (8 bit), masks/ID_m.tif (0/255), split.json."""
    import tifffile

    for d in ("images", "masks"):
        (folder / d).mkdir(parents=True, exist_ok=True)
    for i, img in images.items():
        tifffile.imwrite(folder / "images" / f"{i}.tif", (np.asarray(img) * 255).astype(np.uint8))
    for i, m in masks.items():
        tifffile.imwrite(folder / "masks" / f"{i}_m.tif", np.asarray(m).astype(np.uint8))
    (folder / "split.json").write_text(json.dumps(split))
    return folder


# --- model and inference ----------------------------------------------------------------------------------


@pytest.mark.parametrize("depth, base, size", [(4, 16, (64, 64)), (3, 8, (37, 50)), (1, 4, (5, 7))])
def test_unet_output_shape(depth, base, size):
    from drgan.segmenters.unet import UNet

    net = UNet(1, 3, depth, base).eval()
    assert net(torch.rand(2, 1, *size)).shape == (2, 3, *size)


@pytest.mark.parametrize("depth", [3, 4, 5])
def test_the_unets_receptive_field_is_where_an_output_pixels_gradient_reaches(depth):
    """The smallest extent over output pixels at every position against the poolings' grid (the field shifts with it)."""
    from drgan.segmenters.unet import UNet, receptive_field

    torch.manual_seed(0)
    net = UNet(1, 3, depth, 8).eval()
    extents = []
    for offset in range(2 ** (depth - 1)):
        x = torch.rand(1, 1, 256, 256, requires_grad=True)  # random grey: the ReLUs pass gradients almost everywhere
        net(x)[0, :, 128 + offset, 128 + offset].sum().backward()
        rows, cols = (x.grad[0, 0].abs() > 0).nonzero(as_tuple=True)
        extents += [int(rows.max() - rows.min()) + 1, int(cols.max() - cols.min()) + 1]
    assert min(extents) == receptive_field(depth) and max(extents) <= 1.09 * receptive_field(depth)


def test_auto_depth_takes_the_smallest_depth_whose_field_spans_the_particles():
    from drgan.segmenters.unet import FIELD_PER_DIAMETER, auto_depth, receptive_field

    edge = receptive_field(4) / FIELD_PER_DIAMETER  # 73.6 px
    assert auto_depth(24.0)[0] == auto_depth(edge)[0] == 4
    assert auto_depth(edge + 0.1)[0] == auto_depth(150.0)[0] == 5
    assert auto_depth(1000.0) == (5, auto_depth(1000.0)[1]) and "at most depth 5" in auto_depth(1000.0)[1]
    assert auto_depth(None)[0] == auto_depth(float("nan"))[0] == 4


def test_segment_with_depth_auto_builds_the_depth_its_pairs_particles_need(tmp_path):
    """Large particles (~90 px) get depth 5, recorded in metrics.json and the checkpoint; small ones depth 4, the
    very network (weights and all) a run with depth 4 given trains."""
    from conftest import compose
    from test_closed_loop import make_labelled_set

    from drgan.segment import segment
    from drgan.segmenters.module import load_segmenter

    def run(data, name, depth):
        out = tmp_path / name
        extra = ("trainer.max_epochs=1", "check_fraction=0", "split_calibration.max_pairs=2")
        overrides = [o for o in tiny_segment_overrides(data, tmp_path, out, *extra) if o != "model.depth=2"]
        segment(compose([*overrides, f"model.depth={depth}"], config_name="segment"))
        return json.loads((out / "metrics.json").read_text()), load_segmenter(out / "checkpoints" / "last.ckpt")

    large = tmp_path / "large"
    for d in ("images", "masks", "labels"):
        (large / d).mkdir(parents=True)
    for i in range(8):
        labels = disc_labels(160, n=1, radius=45.0, seed=i)
        Image.fromarray((disc_image(labels, i) * 255).astype(np.uint8)).save(large / "images" / f"{i:03d}.png")
        Image.fromarray(class_mask(labels, 1)).save(large / "masks" / f"{i:03d}.png")
        Image.fromarray(labels.astype(np.uint8)).save(large / "labels" / f"{i:03d}.png")
    metrics, model = run(large, "large", "auto")
    assert metrics["depth"]["value"] == 5 and "receptive field 188 px" in metrics["depth"]["why"]
    assert model.net.depth == 5

    small = make_labelled_set(tmp_path / "small", n=8)
    metrics, model = run(small, "small", "auto")
    assert metrics["depth"]["value"] == 4 and model.net.depth == 4
    given_metrics, given = run(small, "given", 4)
    assert "depth" not in given_metrics
    for key, value in given.state_dict().items():
        assert torch.equal(value, model.state_dict()[key]), key


def test_training_steps_reduce_loss():
    from drgan.segmenters.module import SegmenterModule
    from drgan.segmenters.pairs import CropDataset, Pair

    torch.manual_seed(0)
    pairs = [Pair(str(i), disc_image(disc_labels(seed=i), i), class_mask(disc_labels(seed=i), 1)) for i in range(4)]
    data = CropDataset(pairs, crop=32, augment=True)
    batch = [torch.stack(x) for x in zip(*(data[i] for i in range(4)))]
    model = SegmenterModule(depth=3, base=8, lr=1e-2)
    opt = model.configure_optimizers()
    losses = []
    for _ in range(25):
        opt.zero_grad()
        loss = model._losses(batch)[3]
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0], losses


# --- the ignore value (255) in masks -------------------------------------------------------------------------


def hand_losses(logits: torch.Tensor, target: torch.Tensor, eps: float = 1.0) -> tuple[float, float]:
    """Cross-entropy and soft Dice loss by hand, pixel by pixel, over the pixels whose target is not 255."""
    probs = logits.double().softmax(1).numpy()
    target = target.numpy()
    n_classes = probs.shape[1]
    ce, count = 0.0, 0
    inter, total = np.zeros(n_classes), np.zeros(n_classes)
    for b, y, x in np.ndindex(target.shape):
        t = target[b, y, x]
        if t == 255:
            continue
        ce -= np.log(probs[b, t, y, x])
        count += 1
        for c in range(n_classes):
            inter[c] += probs[b, c, y, x] * (t == c)
            total[c] += probs[b, c, y, x] + (t == c)
    return ce / max(count, 1), 1.0 - float(np.mean((2 * inter + eps) / (total + eps)))


def test_the_extent_dice_is_the_two_class_dice_of_background_and_particle_plus_contour():
    from drgan.segmenters.module import SegmenterModule, extent_dice_loss

    torch.manual_seed(0)
    logits = torch.randn(2, 3, 6, 6)
    target = torch.randint(0, 3, (2, 6, 6))
    target[0, :2] = 255
    probs = logits.double().softmax(1).numpy()
    valid = target.numpy() != 255
    fg_p, fg_t = (probs[:, 1] + probs[:, 2])[valid], (target.numpy() > 0)[valid] * 1.0
    bg_p, bg_t = probs[:, 0][valid], 1.0 - fg_t
    by_hand = 1 - np.mean([(2 * (p * t).sum() + 1) / (p.sum() + t.sum() + 1) for p, t in ((bg_p, bg_t), (fg_p, fg_t))])
    assert float(extent_dice_loss(logits, target)) == pytest.approx(by_hand, rel=1e-5)
    # how the extent's probability is shared between particle and contour does not move it
    moved = logits.clone()
    moved[:, 1] = torch.logaddexp(logits[:, 1], logits[:, 2]) - np.log(2)
    moved[:, 2] = moved[:, 1]
    assert float(extent_dice_loss(moved, target)) == pytest.approx(float(extent_dice_loss(logits, target)), rel=1e-5)
    with pytest.raises(ConfigError, match="model.dice"):
        SegmenterModule(dice="contour")


def test_losses_and_val_dsc_leave_ignored_pixels_out():
    import torch.nn.functional as F

    from drgan.scene.labels import IGNORE
    from drgan.segmenters.module import cross_entropy, particle_dsc, soft_dice_loss

    gen = torch.Generator().manual_seed(0)
    target = torch.randint(0, 3, (2, 6, 5), generator=gen)
    ignored = torch.rand(2, 6, 5, generator=gen) < 0.3
    masked = target.masked_fill(ignored, IGNORE)
    logits = torch.randn(2, 3, 6, 5, generator=gen)
    ce, dice = hand_losses(logits, masked)
    assert cross_entropy(logits, masked).item() == pytest.approx(ce, rel=1e-5)
    assert soft_dice_loss(logits, masked).item() == pytest.approx(dice, rel=1e-5)

    # A prediction wrong only on ignored pixels scores like a perfect one ...
    def confident(classes):
        return 8.0 * F.one_hot(classes, 3).permute(0, 3, 1, 2).float()

    perfect = confident(target)
    wrong = torch.where(ignored[:, None], confident((target + 1) % 3), perfect)
    for loss in (cross_entropy, soft_dice_loss):
        assert loss(wrong, masked).item() == pytest.approx(loss(perfect, masked).item(), abs=1e-7)
        assert loss(wrong, target).item() > loss(perfect, target).item() + 0.1  # ... which it is not, unignored
    assert particle_dsc(wrong, masked).item() == 1.0 and particle_dsc(wrong, target).item() < 1.0


def test_an_all_ignored_crop_gives_a_finite_loss_and_gradients():
    from drgan.scene.labels import IGNORE
    from drgan.segmenters.module import SegmenterModule, cross_entropy, particle_dsc, soft_dice_loss

    torch.manual_seed(0)
    model = SegmenterModule(depth=2, base=4)
    image = torch.rand(2, 1, 16, 16)
    mask = torch.full((2, 16, 16), IGNORE, dtype=torch.int64)
    logits, ce, dice, loss = model._losses((image, mask))
    loss.backward()
    assert ce.item() == 0.0 and dice.item() == 0.0 and loss.item() == 0.0
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() and not g.any() for g in grads)
    assert particle_dsc(logits, mask).item() == 1.0
    # Beside a labelled crop, an all-ignored one changes nothing: the losses are those of the labelled crop alone.
    labels = torch.from_numpy(class_mask(disc_labels(16, n=1, seed=1), 1).astype(np.int64))
    batch = torch.stack([labels, mask[0]])
    logits = torch.randn(2, 3, 16, 16)
    for loss in (cross_entropy, soft_dice_loss):
        assert loss(logits, batch).item() == pytest.approx(loss(logits[:1], batch[:1]).item(), rel=1e-6)


def test_contact_pixels_are_the_line_between_touching_particles_and_narrow_gaps():
    from drgan.scene.labels import IGNORE
    from drgan.segmenters.module import contact_pixels

    # class_mask draws a 1-px contour inside each instance: two touching 6 x 6 squares have a 2-px contour line
    # between their interiors; a pair with 3 background columns between them has 5 non-particle columns between
    # their interiors (contour, 3 background, contour); a lone square has particle on one side of its outline only.
    labels = np.zeros((24, 40), np.int32)
    labels[3:9, 3:9], labels[3:9, 9:15] = 1, 2  # touching
    labels[15:21, 3:9] = 3  # alone (6 rows below the pair)
    labels[3:9, 22:28], labels[3:9, 31:37] = 4, 5  # 3 columns of background between them
    target = torch.from_numpy(class_mask(labels, 1).astype(np.int64))[None]
    assert (target[0, 4:8, 8:10] == 2).all() and (target[0, 4:8, 28:31] == 0).all()
    expected = np.zeros((24, 40), bool)
    expected[4:8, 8:10] = True  # the contact line, beside the interiors (rows 4-7)
    expected[4:8, 29] = True  # the gap's middle column: interiors 3 px away on either side
    contact = contact_pixels(target, reach=3)[0].numpy()
    np.testing.assert_array_equal(contact, expected)
    # reach 2: the contact line still, the gap no more
    expected[4:8, 29] = False
    np.testing.assert_array_equal(contact_pixels(target, reach=2)[0].numpy(), expected)
    # Ignored pixels are never contact pixels.
    ignored = target.clone()
    ignored[0, 4:8, 8] = IGNORE
    assert not contact_pixels(ignored, reach=3)[0, 4:8, 8].any() and contact_pixels(ignored, reach=3)[0, 4:8, 9].all()
    with pytest.raises(ValueError, match="reach=0"):
        contact_pixels(target, reach=0)


def test_contact_weighted_cross_entropy_matches_a_hand_computation_and_trains_the_contact_harder():
    import torch.nn.functional as F

    from drgan.scene.labels import IGNORE
    from drgan.segmenters.module import SegmenterModule, contact_pixels, cross_entropy

    gen = torch.Generator().manual_seed(3)
    labels = np.zeros((16, 16), np.int32)
    labels[2:14, 2:8], labels[2:14, 8:14] = 1, 2
    target = torch.from_numpy(class_mask(labels, 1).astype(np.int64))[None].repeat(2, 1, 1)
    target[1, :3] = IGNORE
    logits = torch.randn(2, 3, 16, 16, generator=gen)
    weight = 1.0 + 4.0 * contact_pixels(target).float()
    per_pixel = F.cross_entropy(logits, torch.where(target == IGNORE, 0, target), reduction="none").double()
    valid = (target != IGNORE).double()
    hand = float((weight.double() * valid * per_pixel).sum() / (weight.double() * valid).sum())
    assert cross_entropy(logits, target, weight=weight).item() == pytest.approx(hand, rel=1e-6)
    assert cross_entropy(logits, target, weight=torch.ones(2, 16, 16)).item() == pytest.approx(
        cross_entropy(logits, target).item(), rel=1e-6
    )
    # A prediction that misses only the contact line costs more with the weight than without it.
    perfect = 8.0 * F.one_hot(torch.where(target == IGNORE, 0, target), 3).permute(0, 3, 1, 2).float()
    contact = contact_pixels(target)
    merged = torch.where(contact[:, None], 8.0 * F.one_hot(torch.ones_like(target), 3).permute(0, 3, 1, 2), perfect)
    plain = SegmenterModule(depth=2, base=4)
    weighted = SegmenterModule(depth=2, base=4, contact_weight=9.0)
    assert weighted.hparams.contact_weight == 9.0 and plain.hparams.contact_weight == 0.0
    ratio = cross_entropy(merged, target, weight=1.0 + 9.0 * contact.float()) / cross_entropy(merged, target)
    share = contact.sum() / (target != IGNORE).sum()
    # (the right pixels' cross-entropy, ~1e-3 each at logit 8, makes it approximate)
    assert ratio.item() == pytest.approx(10.0 / (1 + 9.0 * share.item()), rel=0.01) and ratio.item() > 4
    # The module's loss uses it: the same logits give a higher loss on the merged prediction.
    image = torch.rand(2, 1, 16, 16, generator=gen)
    torch.manual_seed(0)
    a = SegmenterModule(depth=2, base=4)
    torch.manual_seed(0)
    b = SegmenterModule(depth=2, base=4, contact_weight=9.0)
    _, ce_a, _, _ = a._losses((image, target))
    _, ce_b, _, _ = b._losses((image, target))
    logits = a(image).detach()
    assert ce_a.item() == pytest.approx(cross_entropy(logits, target).item(), rel=1e-5)
    assert ce_b.item() == pytest.approx(
        cross_entropy(logits, target, weight=1.0 + 9.0 * contact.float()).item(), rel=1e-5
    )
    for bad, match in ((-1.0, "contact_weight=-1.0"), (float("nan"), "contact_weight=nan")):
        with pytest.raises(ConfigError, match=match):
            SegmenterModule(depth=2, base=4, contact_weight=bad)
    with pytest.raises(ConfigError, match="contact_reach=0"):
        SegmenterModule(depth=2, base=4, contact_reach=0)


def test_crops_carry_the_ignore_value_unchanged():
    from drgan.scene.labels import IGNORE
    from drgan.segmenters.pairs import CropDataset, Pair

    rng = np.random.default_rng(0)
    mask = rng.choice(np.array([0, 1, 2, IGNORE], np.uint8), size=(20, 20))
    grey = {0: 0.1, 1: 0.4, 2: 0.6, IGNORE: 0.9}  # each class its own grey: image and mask must stay aligned
    image = np.vectorize(grey.get)(mask).astype(np.float32)
    for crop in (20, 24, 12):  # the whole image rotated and flipped, reflect-padded, cut
        data = CropDataset(
            [Pair("a", image, mask)], crop=crop, augment=True, samples_per_pair=12, brightness=0, contrast=0
        )
        for k in range(len(data)):
            x, y = data[k]
            x, y = x[0].numpy(), y.numpy()
            assert set(np.unique(y).tolist()) <= {0, 1, 2, IGNORE}
            for value, level in grey.items():
                np.testing.assert_allclose(x[y == value], level, atol=1e-6)
            if crop == 20:
                assert (
                    np.bincount(y.ravel(), minlength=256).tolist() == np.bincount(mask.ravel(), minlength=256).tolist()
                )


def test_texture_augmentation_adds_correlated_noise_of_bounded_std_and_leaves_masks_alone():
    from drgan.segmenters.pairs import TEXTURE_PX, CropDataset, Pair, surface_texture

    rng = np.random.default_rng(1)
    stds, lags = [], []
    for _ in range(200):
        field = surface_texture((64, 64), 0.1, rng)
        stds.append(field.std())
        lags.append(np.corrcoef(field[:, :-1].ravel(), field[:, 1:].ravel())[0, 1])
    assert 0 <= min(stds) and max(stds) <= 0.1 + 1e-9 and 0.04 < np.mean(stds) < 0.06  # uniform in [0, 0.1]
    # low-passed at 0.7-3 px: neighbours correlate (white noise: 0), from grain (weakly) to cracks (strongly)
    assert min(lags) > 0.3 and max(lags) > 0.9 and TEXTURE_PX == (0.7, 3.0)
    mask = (np.add.outer(np.arange(32), np.arange(32)) % 7 == 0).astype(np.uint8)
    image = np.where(mask == 1, 0.7, 0.3).astype(np.float32)
    plain = CropDataset([Pair("a", image, mask)], 32, augment=True, samples_per_pair=20, brightness=0, contrast=0)
    textured = CropDataset(
        [Pair("a", image, mask)], 32, augment=True, samples_per_pair=20, brightness=0, contrast=0, texture=0.1
    )
    for k in range(20):
        x, y = plain[k]
        assert (np.isclose(x, 0.3) | np.isclose(x, 0.7)).all()  # without texture: the two grey levels only
        x, y = textured[k]
        assert set(np.unique(y.numpy())) <= {0, 1}
        residual = x[0].numpy() - np.where(y.numpy() == 1, 0.7, 0.3)  # image and mask still aligned
        assert np.abs(residual).max() < 0.6 and residual.std() <= 0.1 + 1e-6
    assert any(np.abs(textured[k][0].numpy()[0] - np.where(textured[k][1].numpy() == 1, 0.7, 0.3)).max() > 0.01
               for k in range(20))  # fmt: skip
    # validation crops are never textured (repeatable scores)
    val = CropDataset([Pair("a", image, mask)], 32, augment=False, texture=0.1)
    np.testing.assert_array_equal(val[0][0][0].numpy(), image)


def test_contact_shading_dips_touching_particles_only_and_follows_the_crop():
    """loader.contact_shade: the ridge between two touching instances (hand-made: a touching pair, a pair 1 px apart
    as annotators separate them, a lone particle and one cut by the border) is pulled towards the background grey by
    the drawn depth; every other pixel stays; the masks are never touched; a depth above 1 is refused."""
    from scipy import ndimage as ndi

    from drgan.segmenters.pairs import CropDataset, Pair, contact_ridge, shade_contacts

    labels = np.zeros((32, 32), np.int32)
    labels[4:12, 2:8], labels[4:12, 8:14] = 1, 2  # touching along the column 7 | 8
    labels[18:26, 2:8], labels[18:26, 9:15] = 3, 4  # a 1 px line (column 8) between them
    labels[4:12, 20:28] = 5  # alone
    labels[28:32, 20:28] = 6  # cut by the border, alone
    ridge = contact_ridge(labels)
    assert ridge[4:12, 7:9].all() and ridge[18:26, 8].all()  # both sides of the touching pair; the separating line
    # ... and the background pixels just beyond each contact's two ends (both particles within 1 px), nothing else
    assert ridge.sum() == (8 * 2 + 2 * 2) + (8 + 2 * 1)
    assert not ridge[:, 16:].any()
    mask = (labels > 0).astype(np.uint8)
    image = np.where(mask == 1, 0.8, 0.2).astype(np.float32)
    shaded = shade_contacts(image, labels, mask, 0.5)
    assert shaded[8, 7] == pytest.approx(0.8 + 0.5 * (0.2 - 0.8), abs=1e-3)  # the ridge: halfway to the background
    assert shaded[21, 8] == pytest.approx(0.2, abs=1e-6)  # background pixels already at the background grey
    far = ~ndi.binary_dilation(ridge, iterations=3)
    np.testing.assert_allclose(shaded[far], image[far], atol=1e-6)  # a Gaussian 0.7 px wide: gone 3 px away
    np.testing.assert_array_equal(shade_contacts(image, labels, mask, 0.0), image)
    lone = np.where(labels == 5, 5, 0)
    np.testing.assert_array_equal(shade_contacts(image, lone, mask, 1.0), image)  # no contact: unchanged
    # in the loader: crops of a generated pair with its instances; masks alike with and without, images differ
    pair = Pair("a", image, mask, labels)
    plain = CropDataset([pair], 32, augment=True, samples_per_pair=8, brightness=0, contrast=0, texture=0)
    shaded_set = CropDataset(
        [pair], 32, augment=True, samples_per_pair=8, brightness=0, contrast=0, texture=0, contact_shade=1.0
    )
    dips = []
    for k in range(8):
        x, y = shaded_set[k]
        assert set(np.unique(y.numpy())) <= {0, 1} and int((y == 1).sum()) == int(mask.sum())
        dips.append(float(0.8 - x[0].numpy()[y.numpy() == 1].min()))
        assert x[0].numpy().min() >= 0.2 - 1e-6 and x[0].numpy().max() <= 0.8 + 1e-6
    assert max(dips) > 0.05  # depths drawn from [0, 1]: some crop dips
    for k in range(4):  # without: the two grey levels only
        x = plain[k][0].numpy()
        assert (np.isclose(x, 0.2) | np.isclose(x, 0.8)).all()
    from drgan.segment import LoaderSettings

    cfg = compose(["loader.contact_shade=1.5"], config_name="segment")
    with pytest.raises(ConfigError, match=r"loader.contact_shade=1.5: expected a number in \[0, 1\]"):
        LoaderSettings.from_config(cfg)


def test_sliding_window_matches_direct_inference():
    from drgan.segmenters.inference import predict, predict_probs
    from drgan.segmenters.unet import UNet

    torch.manual_seed(0)
    net = UNet(1, 3, 3, 4).eval()
    image = np.random.default_rng(0).random((32, 32)).astype(np.float32)
    direct = net(torch.from_numpy(image)[None, None]).softmax(1)[0].detach().numpy()
    np.testing.assert_allclose(predict_probs(net, image, tile=32), direct, atol=1e-5)
    # Sizes not multiple of the tile, and smaller than one tile: full coverage, probabilities sum to 1.
    for shape in [(50, 71), (20, 45)]:
        probs = predict_probs(
            net, np.random.default_rng(1).random(shape).astype(np.float32), tile=32, overlap=0.5, batch_size=3
        )
        assert probs.shape == (3, *shape) and np.isfinite(probs).all()
        np.testing.assert_allclose(probs.sum(0), 1.0, atol=1e-5)
    assert predict(net, image, tile=32).dtype == np.uint8


def test_mirrored_inference_is_the_mean_over_four_mirror_images_and_mirror_equivariant():
    from drgan.segmenters.inference import make_predictor, predict_probs
    from drgan.segmenters.unet import UNet

    torch.manual_seed(0)
    net = UNet(1, 3, 3, 4).eval()  # random weights: not mirror-symmetric, so a missing flip-back shows
    image = np.random.default_rng(0).random((32, 32)).astype(np.float32)
    x = torch.from_numpy(image)[None, None]
    with torch.no_grad():
        by_hand = sum(net(x.flip(d)).softmax(1).flip(d) for d in ((), (-1,), (-2,), (-2, -1)))[0].numpy() / 4
    mirrored = predict_probs(net, image, tile=32, mirror=True)
    np.testing.assert_allclose(mirrored, by_hand, atol=1e-5)
    plain = predict_probs(net, image, tile=32)
    assert np.abs(plain - mirrored).max() > 1e-3  # the network alone is not mirror-symmetric
    # mirrored inference of a mirrored image is the mirror of the prediction (tiles covering the image exactly)
    np.testing.assert_allclose(
        predict_probs(net, image[:, ::-1].copy(), tile=32, mirror=True), mirrored[:, :, ::-1], atol=1e-5
    )
    assert not np.allclose(predict_probs(net, image[:, ::-1].copy(), tile=32), plain[:, :, ::-1], atol=1e-3)
    make_predictor(net, {"mirror": True, "tile": 32})  # a known inference setting
    with pytest.raises(ConfigError, match=r"inference.mirror='yes': expected true or false"):
        make_predictor(net, {"mirror": "yes"})


def test_zscore_segmenter_ignores_detector_brightness_and_contrast():
    """A "zscore" model predicts the same on a*x + b as on x (whole-image statistics, at inference as in
    training crops); the raw "none" model does not, so the check can fail."""
    from drgan.core.errors import ConfigError
    from drgan.segmenters.inference import predict_probs
    from drgan.segmenters.module import SegmenterModule
    from drgan.segmenters.pairs import CropDataset, Pair

    labels = disc_labels(size=48, n=4)
    image = disc_image(labels)
    darker = 0.25 * image + 0.02  # a different detector setting: 4x less contrast, an offset
    for mode, same in (("zscore", True), ("none", False)):
        torch.manual_seed(0)
        model = SegmenterModule(depth=3, base=4, normalize=mode).eval()
        a, b = predict_probs(model, image, tile=32, overlap=0.5), predict_probs(model, darker, tile=32, overlap=0.5)
        assert np.allclose(a, b, atol=1e-4) == same, (mode, np.abs(a - b).max())
    # The training crops are normalised with the statistics of their whole image, not of the crop.
    pair = Pair("a", image, class_mask(labels, 1))
    crop = CropDataset([pair], crop=16, augment=False, normalize="zscore")[0][0][0].numpy()
    centre = image[16:32, 16:32]
    np.testing.assert_allclose(crop, (centre - image.mean()) / image.std(), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(CropDataset([pair], crop=16, augment=False)[0][0][0].numpy(), centre)
    with pytest.raises(ConfigError, match="model.normalize.*zscore"):
        SegmenterModule(normalize="minmax")
    with pytest.raises(ConfigError, match="loader normalize"):
        CropDataset([pair], crop=16, augment=False, normalize="percentile")


def _two_touching_discs(size=48, r=9.0, gap=14.0):
    """Labels of two discs whose centres are `gap` px apart (< 2 r: they overlap, the second wins)."""
    yy, xx = np.mgrid[:size, :size]
    labels = np.zeros((size, size), np.int32)
    c = size / 2
    for k, cx in enumerate((c - gap / 2, c + gap / 2)):
        labels[(yy - c) ** 2 + (xx - cx) ** 2 <= r * r] = k + 1
    return labels


def _probs_of(particle: np.ndarray, contour: np.ndarray | None = None) -> np.ndarray:
    """(3, H, W) one-hot-ish probabilities: 0.9 on the given class, the rest shared."""
    contour = np.zeros(particle.shape, bool) if contour is None else contour
    cls = np.where(contour, 2, np.where(particle, 1, 0))
    probs = np.full((3, *particle.shape), 0.05, np.float32)
    np.put_along_axis(probs, cls[None], 0.9, axis=0)
    return probs


def test_separate_regions_gives_one_4_connected_instance_per_region():
    from drgan.metrics.instance_scores import binarize_and_label
    from drgan.segmenters.inference import separate_regions

    labels = np.zeros((6, 8), np.int32)
    labels[1:5, 1:4] = 1
    labels[1:5, 4:7] = 2  # shares a 4-px vertical edge with region 1
    cm = separate_regions(labels)
    # exactly the 4 pixels of region 2 next to region 1 (column 4, rows 1-4) become line
    assert (cm == 2).sum() == 4 and (cm[1:5, 4] == 2).all()
    assert ((cm > 0) == (labels > 0)).all()  # nothing leaves the foreground
    assert binarize_and_label(cm.astype(np.int64)).max() == 2
    # a merged blob of the argmax would be one instance
    assert binarize_and_label((labels > 0).astype(np.int64)).max() == 1


def test_a_particles_holes_are_its_own_but_gaps_between_particles_and_particles_inside_a_ring_stay():
    from drgan.segmenters.inference import filled_holes

    classes = np.zeros((20, 30), np.uint8)
    classes[2:9, 2:9] = 1
    classes[4:7, 4:6] = 0  # a hole in a particle
    classes[5, 6] = 2  # and a contour pixel beside it: part of the hole all the same
    classes[2:12, 12:22] = 1
    classes[4:10, 14:20] = 2  # a ring's inside drawn as contour ...
    classes[6:8, 16:18] = 1  # ... around a small particle: both stay
    for rows, cols in (((13, 18), slice(2, 8)), ((13, 18), slice(9, 15))):  # two brackets, [ and ], facing: the
        classes[rows[0], cols] = classes[rows[1], cols] = 1  # background between them is enclosed by both together,
    classes[13:19, 2] = classes[13:19, 14] = 1  # by neither alone
    classes[13, 8] = classes[18, 8] = 2  # (their joints: the contour class)
    filled = filled_holes(classes)
    assert (filled[2:9, 2:9] == 1).all()  # the hole filled
    np.testing.assert_array_equal(filled[2:12, 12:22], classes[2:12, 12:22])  # the ring with a particle inside kept
    changed = filled != classes
    assert changed.sum() == 3 * 2 + 1 == changed[2:9, 2:9].sum()  # only the first particle's hole
    # what the particle table measures is then what ImageJ's traced ROI of the particle covers
    from drgan.data.imagej import fill_polygon, traced_outline
    from drgan.metrics.instance_scores import binarize_and_label

    labels = binarize_and_label(filled.astype(np.int64))
    first = labels == labels[3, 3]
    assert fill_polygon(traced_outline(first), first.shape).sum() == first.sum()


def test_split_touching_separates_a_merged_pair_and_keeps_single_particles():
    from drgan.metrics.instance_scores import binarize_and_label, match_instances
    from drgan.segmenters.inference import split_touching

    truth = _two_touching_discs()
    merged = _probs_of(truth > 0)  # the network drew no line between them
    assert binarize_and_label(merged.argmax(0).astype(np.int64)).max() == 1
    pred = binarize_and_label(split_touching(merged).astype(np.int64))
    m = match_instances(pred, truth, 0.5)
    assert m.tp == 2 and m.fp == 0 and m.fn == 0 and m.ious.min() > 0.8
    # one round particle stays one
    yy, xx = np.mgrid[:40, :40]
    disc = (yy - 20) ** 2 + (xx - 20) ** 2 <= 100
    assert binarize_and_label(split_touching(_probs_of(disc)).astype(np.int64)).max() == 1
    # contour pixels count as foreground (the particle keeps its rim) and seed nothing by themselves
    rim = disc & ~((yy - 20) ** 2 + (xx - 20) ** 2 <= 64)
    cm = split_touching(_probs_of(disc, contour=rim))
    assert ((cm > 0) == disc).all()
    assert not split_touching(_probs_of(np.zeros((20, 20), bool), contour=disc[:20, :20])).any()


def test_specks_go_to_the_neighbour_sharing_the_most_border_or_are_dropped():
    from drgan.data.classical.watershed import merge_specks

    labels = np.zeros((12, 16), np.int64)
    labels[1:11, 1:6] = 1  # a particle of 50 px ...
    labels[1:11, 9:15] = 2  # ... and one of 60
    labels[4:7, 6:9] = 3  # a 9-px region between them: kept at min_px 8
    np.testing.assert_array_equal(merge_specks(labels, 8), labels)
    labels[4:7, 6:9] = 0
    sliver = np.zeros_like(labels, bool)
    sliver[4:6, 6] = sliver[5, 7:9] = True  # a 4-px sliver: 4 px of border with particle 1, 3 with particle 2
    labels[sliver] = 3
    labels[11, 7] = 4  # a 1-px speck touching nothing
    out = merge_specks(labels, 8)
    assert (out[sliver] == 1).all() and out[11, 7] == 0
    np.testing.assert_array_equal(out[labels <= 2], labels[labels <= 2])  # the particles keep their pixels
    assert (merge_specks(labels, 0) == labels).all()  # off


def test_a_core_sliver_seeds_no_false_particle_of_its_own():
    """`components` keeps a seed in every piece of the core; a sliver of core the contour class cut off beside a
    particle then floods a few pixels: merged into the particle, not a false one (AP50) nor a lost pixel."""
    from drgan.metrics.instance_scores import binarize_and_label
    from drgan.segmenters.inference import split_touching

    yy, xx = np.mgrid[:40, :40]
    disc = (yy - 20) ** 2 + (xx - 20) ** 2 <= 100
    contour = disc & (xx == 27)  # a line across the disc cuts off a 3-px-wide cap ...
    probs = _probs_of(disc, contour=contour)
    cap = disc & (xx > 27)
    assert 8 <= cap.sum()  # ... a particle of its own when large enough
    for rule in ("hmaxima", "components"):
        labels = binarize_and_label(split_touching(probs, 1.0, 1.0, None, rule, min_px=cap.sum() + 1).astype(np.int64))
        assert labels.max() == 1, rule
        assert (labels > 0).sum() >= disc.sum() - contour.sum() - 2  # the cap's pixels went to the particle
    kept = binarize_and_label(split_touching(probs, 1.0, 1.0, None, "components", min_px=1).astype(np.int64))
    assert kept.max() == 2  # without the rule the cap is a particle: what the rule removes


class _Threshold(torch.nn.Module):
    """A stand-in segmenter: particle where the image is above 0.5; records the size of every tile it sees."""

    def __init__(self):
        super().__init__()
        self.seen: list[tuple[int, int]] = []

    def forward(self, x):
        self.seen.append(tuple(x.shape[-2:]))
        z = (x - 0.5) * 40
        return torch.cat([-z, z, torch.full_like(z, -20.0)], 1)


def test_a_segmenter_of_large_particles_sees_the_image_at_its_pixel_scale_and_answers_at_the_image_size():
    """Pairs rendered at half the real px (a wide view of large particles) give a segmenter of pixel_scale 0.5: it
    must see real images halved, and its class map, outlines and touching-particle split come back at full size."""
    from drgan.metrics.instance_scores import binarize_and_label, match_instances
    from drgan.segmenters.inference import make_predictor, predict

    truth = _two_touching_discs(size=96, r=22.0, gap=34.0)
    image = np.where(truth > 0, 0.8, 0.2).astype(np.float32)
    model = _Threshold()
    model.pixel_scale = 0.5  # as load_segmenter sets it from the checkpoint
    classes = predict(model, image, tile=48, split="watershed", split_depth=2.0, split_core=None)
    assert set(model.seen) == {(48, 48)} and len(model.seen) == 1  # one 48 px tile: the 96 px image halved
    assert classes.shape == truth.shape
    assert abs(int((classes > 0).sum()) / int((truth > 0).sum()) - 1) < 0.03  # the outline where it was
    pred = binarize_and_label(classes.astype(np.int64))
    m = match_instances(pred, truth, 0.5)
    assert m.tp == 2 and m.fp == 0 and m.ious.min() > 0.85  # the split still cuts the pair at full size
    # an inference setting overrides the model's own; a bad one is refused before any image
    model.seen.clear()
    make_predictor(model, {"tile": 96, "pixel_scale": 1.0})(image)
    assert model.seen == [(96, 96)]
    with pytest.raises(ConfigError, match="pixel_scale"):
        make_predictor(model, {"pixel_scale": 0})


def test_per_image_scale_brings_each_images_particles_to_the_training_diameter(monkeypatch):
    """A segmenter that learned 20-px particles at pixel scale 0.5 (larger particles shrunk to its working
    diameter) halves an image of 12-px particles to 6-px ones. pixel_scale=per_image measures them on that first
    pass and predicts the image once more at the scale that brings them to 20 px. An image of training-size
    particles keeps the first pass, even with specks beside them (the area-weighted median is the particles'), and
    so do one with too few particles to measure and one of larger particles (only enlarging: merges measure
    large)."""
    from drgan.metrics.instance_scores import binarize_and_label, match_instances
    from drgan.segmenters import inference
    from drgan.segmenters.inference import make_predictor, predict, resolve_pixel_scale

    scales: list[float] = []
    real_resample = inference.resample
    monkeypatch.setattr(inference, "resample", lambda image, scale: scales.append(scale) or real_resample(image, scale))
    model = _Threshold()
    model.pixel_scale, model.working_diameter = 0.5, 20.0
    small = disc_labels(96, n=6, radius=6.0, seed=3)  # 12-px particles
    settings = {"tile": 64, "split": "watershed", "split_core": None, "annotations": False, "pixel_scale": "per_image"}
    classes = make_predictor(model, settings)(disc_image(small))
    assert scales[0] == 0.5 and len(scales) == 2 and 1.4 < scales[1] < 2.0  # 20 / ~12 px
    m = match_instances(binarize_and_label(classes.astype(np.int64)), small, 0.5)
    assert m.tp == small.max() and m.fp == 0
    scales.clear()
    large = disc_labels(192, n=3, radius=20.0, seed=3)  # 40-px particles: 20 px at 0.5 already
    image = disc_image(large)
    for y, x in ((4, 4), (4, 180), (180, 4), (180, 180)):  # four 4 x 4 px specks: the plain median would be theirs
        image[y : y + 4, x : x + 4] = 0.9
    predict(model, image, **settings)
    assert scales == [0.5]
    scales.clear()
    predict(model, disc_image(disc_labels(96, n=2, radius=6.0, seed=3)), **settings)  # two particles measure nothing
    assert scales == [0.5]
    scales.clear()
    predict(model, disc_image(disc_labels(192, n=3, radius=40.0, seed=3)), **settings)  # larger ones: never shrunk
    assert scales == [0.5]
    # auto: per_image for the instance-aware segmenter (one working diameter learnt), the own scale for the U-Net
    assert resolve_pixel_scale(model, "auto") is None and resolve_pixel_scale(model, 0.7) == 0.7
    model.needs_centres = True
    assert resolve_pixel_scale(model, "auto") == "per_image"
    del model.working_diameter  # a checkpoint from before it was stored: refused before any image
    assert resolve_pixel_scale(model, "auto") is None
    with pytest.raises(ConfigError, match="per_image: this segmenter's checkpoint stores no working diameter"):
        make_predictor(model, settings)
    with pytest.raises(ConfigError, match="pixel_scale='large'"):
        make_predictor(model, {"pixel_scale": "large"})


def test_particles_on_a_figures_panel_letters_are_dropped_as_the_classical_segmentation_drops_them():
    """Figure crops carry panel letters and scale-bar text in pure white, which a segmenter of bright particles
    reads as particles. Inference drops what lies on the annotations the classical segmentation finds, unless told
    not to."""
    from drgan.metrics.instance_scores import binarize_and_label
    from drgan.segmenters.inference import predict

    image = np.full((128, 128), 0.3, np.float32)
    yy, xx = np.mgrid[:128, :128]
    disc = (yy - 70) ** 2 + (xx - 70) ** 2 <= 15**2
    image[disc] = 0.7
    image[4:18, 4:6] = 1.0  # "I"
    for r in range(14):  # "V": two 2 px strokes
        image[4 + r, int(9 + 0.3 * r) : int(11 + 0.3 * r)] = 1.0
        image[4 + r, int(17 - 0.3 * r) : int(19 - 0.3 * r)] = 1.0
    model = _Threshold()
    kept = predict(model, image, tile=128, split="none")
    assert binarize_and_label(kept.astype(np.int64)).max() == 1 and ((kept == 1) == disc).all()
    everything = predict(model, image, tile=128, split="none", annotations=False)
    assert binarize_and_label(everything.astype(np.int64)).max() >= 2 and (everything[4:18, 4:6] == 1).all()


def test_predictor_settings_are_checked_before_predicting():
    from drgan.core.errors import ConfigError
    from drgan.segmenters.inference import make_predictor, predict
    from drgan.segmenters.unet import UNet

    torch.manual_seed(0)  # an untrained net: without a seed its argmax could fall on what looks like an annotation
    net = UNet(1, 3, 2, 4).eval()
    for bad, message in [
        ({"split": "magic"}, "inference.split"),
        ({"split_depth": 0}, "split_depth"),
        ({"tile_size": 32}, "unknown setting"),
    ]:
        with pytest.raises(ConfigError, match=message):
            make_predictor(net, bad)
    image = np.random.default_rng(0).random((32, 32)).astype(np.float32)
    # split="none" is the plain argmax of the probabilities
    from drgan.segmenters.inference import predict_probs

    plain = predict(net, image, split="none", tile=32, annotations=False)
    assert (plain == predict_probs(net, image, tile=32).argmax(0)).all()


# --- evaluation -------------------------------------------------------------------------------------------


def _hand_case(tmp_path):
    """20x20 image: true squares A (rows 2-5, cols 2-5) and B (rows 12-15, cols 12-15).
    Run 'partial' predicts A exactly plus a false square C (rows 2-3, cols 14-15) and misses B:
    TP 1, FP 1, FN 1 -> DSC 2*16/(20+32), AP50 1/3, SQ 1, RQ 1/2, PQ 1/2. Run 'perfect' scores 1."""
    true = np.zeros((20, 20), np.uint8)
    true[2:6, 2:6] = 255
    true[12:16, 12:16] = 255
    image = np.where(true > 0, 0.8, 0.2)
    partial = np.zeros((20, 20), np.uint8)
    partial[2:6, 2:6] = 1
    partial[2:4, 14:16] = 1
    perfect = (true > 0).astype(np.uint8)
    data = make_real(
        tmp_path / "real", {"a": image, "t": image}, {"a": true, "t": true}, {"train": ["t"], "test": ["a"]}
    )
    return data, {"partial": lambda im: partial, "perfect": lambda im: perfect}


def eval_cfg(data, out, extra=()):
    return compose([f"data={data}", f"out={out}", "crop_rows=null", *extra], config_name="evaluate")


def test_evaluate_hand_computed_scores_and_overlay(tmp_path):
    from drgan.evaluate import SCORES, EvaluateSettings, evaluate
    from drgan.metrics.overlays import GREEN, RED, YELLOW

    data, predictors = _hand_case(tmp_path)
    result = evaluate(
        EvaluateSettings.from_config(eval_cfg(data, tmp_path / "out", ["overlay_alpha=1.0"]), need_models=False),
        predictors=predictors,
    )
    part = result["runs"]["partial"]
    assert part["dsc"] == pytest.approx(32 / 52) and part["ap50"] == pytest.approx(1 / 3)
    assert part["pq"] == pytest.approx(0.5) and part["sq"] == pytest.approx(1.0) and part["rq"] == pytest.approx(0.5)
    # Background (stuff): IoU 364/384 = 91/96; particle pixels: IoU 16/36 < 0.5 -> 0 as a stuff class.
    assert part["pq_classes"] == pytest.approx((91 / 96 + 0.5) / 2) and part["pq_semantic"] == pytest.approx(91 / 192)
    assert result["runs"]["perfect"] == {k: pytest.approx(1.0) for k in SCORES}
    assert result["mean"]["ap50"] == pytest.approx((1 / 3 + 1) / 2)
    assert result["std"]["pq"] == pytest.approx(np.std([0.5, 1.0], ddof=1))
    rows = list(csv.DictReader((tmp_path / "out" / "results.csv").open()))
    assert [(r["run"], r["image"]) for r in rows] == [
        ("partial", "a"),
        ("partial", "mean"),
        ("perfect", "a"),
        ("perfect", "mean"),
    ]
    assert (rows[0]["tp"], rows[0]["fp"], rows[0]["fn"]) == ("1", "1", "1")
    md = (tmp_path / "out" / "results.md").read_text()
    assert "0.750 +- 0.354" in md  # PQ over the two runs
    rgb = np.asarray(Image.open(tmp_path / "out" / "overlays" / "a.png"))  # overlay of the first run
    assert tuple(rgb[3, 3]) == GREEN and tuple(rgb[2, 14]) == RED and tuple(rgb[13, 13]) == YELLOW
    assert tuple(rgb[10, 0]) == (51, 51, 51)  # background: the grey image (0.2 * 255)


@pytest.mark.parametrize(
    "case, message",
    [
        ("size", "differs from its image"),
        ("values", "unexpected values"),
        ("missing", "no mask for image id"),
        ("not_segmenter", "not a drgan segmenter checkpoint"),
        ("not_checkpoint", "not a readable PyTorch checkpoint"),
    ],
)
def test_evaluate_refuses_bad_inputs_before_writing(case, message, tmp_path):
    from drgan.evaluate import EvaluateSettings, evaluate

    image, mask = np.full((16, 16), 0.5), np.zeros((16, 16), np.uint8)
    masks = {"a": mask}
    if case == "size":
        masks = {"a": np.zeros((16, 17), np.uint8)}
    elif case == "values":
        masks = {"a": np.array([[0, 128, 255]] * 16 + [[0, 0, 0]] * 0, np.uint8)[:, :3].repeat(6, axis=1)[:, :16]}
    elif case == "missing":
        masks = {}
    data = make_real(tmp_path / "real", {"a": image}, masks, {"train": [], "test": ["a"]})
    ckpt = tmp_path / "model.ckpt"
    if case == "not_checkpoint":
        ckpt.write_text("hello")
    elif case == "not_segmenter":
        torch.save({"state_dict": {}, "hyper_parameters": {"material": "tio2_sem"}}, ckpt)
    out = tmp_path / "out"
    with pytest.raises(DataError, match=message):
        if case.startswith("not_"):
            evaluate(EvaluateSettings.from_config(eval_cfg(data, out, [f"models=[{ckpt}]"])))
        else:
            evaluate(
                EvaluateSettings.from_config(eval_cfg(data, out), need_models=False),
                predictors={"x": lambda im: np.zeros(im.shape, np.uint8)},
            )
    assert not out.exists()


# --- training entry point, checkpoint, evaluation with the real model -------------------------------------


def tiny_segment_overrides(data, root, out, *extra) -> list[str]:
    """Overrides of a segmenter run small enough for tests: a 2-level U-Net with 4 filters on 32 px crops, CPU."""
    return [
        f"data={data}",
        f"out={out}",
        f"paths.root_dir={root}",
        "model.depth=2",
        "model.base=4",
        "loader.crop=32",
        "loader.batch_size=4",
        "trainer.accelerator=cpu",
        "trainer.enable_progress_bar=false",
        *extra,
    ]


def test_segment_trains_resumes_logs_and_evaluates(tmp_path, monkeypatch):
    from drgan.evaluate import EvaluateSettings, evaluate
    from drgan.segment import TrainingPairs, segment

    data = make_generated(tmp_path / "gen")
    # pairs of a GAN that learned from windows twice its render: every checkpoint carries the scale to inference
    monkeypatch.setattr(TrainingPairs, "pixel_scale", lambda self, manifest=None: 0.5)
    monkeypatch.setattr(TrainingPairs, "noise_level", lambda self, pairs, manifest=None: 0.02)
    out = tmp_path / "run"
    common = tiny_segment_overrides(
        data, tmp_path, out, "trainer.log_every_n_steps=1", "name=tiny", "model.normalize=zscore"
    )
    metrics = segment(compose([*common, "trainer.max_epochs=1"], config_name="segment"))
    assert {"train/loss", "val/loss", "val/dsc"} <= set(metrics)
    last = out / "checkpoints" / "last.ckpt"
    assert last.is_file() and json.loads((out / "metrics.json").read_text())["global_step"] == 1
    from drgan.segmenters.module import load_segmenter

    assert load_segmenter(last).input_normalization == "zscore"  # travels with the checkpoint to inference
    # the split chosen on the validation pairs is stored in the checkpoint and read back by evaluate's auto
    calibration = json.loads((out / "metrics.json").read_text())["split_calibration"]
    assert calibration["n_pairs"] >= 1 and len(calibration["table"]) == 2 * 7 * 5  # seeds x cores x depths
    assert load_segmenter(last).split_calibration == calibration
    epoch_file = next((out / "checkpoints").glob("epoch_*.ckpt"))
    assert load_segmenter(last).pixel_scale == load_segmenter(epoch_file).pixel_scale == 0.5
    assert json.loads((out / "metrics.json").read_text())["pixel_scale"] == 0.5
    # and the generated images' fine-noise level (stubbed above): inference brings cleaner images up to it
    assert json.loads((out / "metrics.json").read_text())["noise_level"] == 0.02
    assert load_segmenter(last).train_noise == load_segmenter(epoch_file).train_noise == 0.02
    saved = torch.load(last, map_location="cpu", weights_only=True)["hyper_parameters"]
    assert saved["_target_"] == "drgan.segmenters.module.SegmenterModule"  # the class, for the registry's loader
    again = segment(compose([*common, "trainer.max_epochs=2", "ckpt_path=last"], config_name="segment"))
    assert json.loads((out / "metrics.json").read_text())["global_step"] == 2 and "train/loss" in again

    import mlflow

    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlruns/mlflow.db")
    exp = client.get_experiment_by_name("segment_tiny")
    runs = client.search_runs([exp.experiment_id])
    assert len(runs) == 1  # the resumed run continued the same MLflow run
    assert "model/depth" in runs[0].data.params and "train/loss" in runs[0].data.metrics
    assert [a.path for a in client.list_artifacts(runs[0].info.run_id, "checkpoints")] == ["checkpoints/last.ckpt"]

    labels = disc_labels(40, seed=7)
    real = make_real(
        tmp_path / "real", {"x": disc_image(labels)}, {"x": (labels > 0) * 255}, {"train": [], "test": ["x"]}
    )
    result = evaluate(
        EvaluateSettings.from_config(
            eval_cfg(real, tmp_path / "eval", [f"models=[{last},{last}]", "inference.tile=32"])
        )
    )
    assert set(result["runs"]) == {"run0", "run1"} and result["std"]["dsc"] == pytest.approx(0.0)
    assert "split calibrated on" in (tmp_path / "eval" / "results.md").read_text()
    assert "images resampled by 0.5" in (tmp_path / "eval" / "results.md").read_text()  # says how it was scored
    assert (tmp_path / "eval" / "overlays" / "x.png").is_file()


def with_manifest(folder: Path, polarity: str, clark_evans: float | None = None) -> Path:
    """make_generated's pairs with the manifest.json drgan.generate writes beside them (its config's polarity; its
    material's Clark-Evans ratio when given, as a profiled material's set has it)."""
    entries = [
        {"id": p.stem, "kind": "synthetic", "files": {"image": f"images/{p.name}", "mask": f"masks/{p.name}"}}
        for p in sorted((folder / "images").glob("*.png"))
    ]
    manifest = {"config": {"polarity": polarity}, "entries": entries}
    if clark_evans is not None:
        manifest["material"] = {"name": "made", "clark_evans": clark_evans}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def test_the_same_command_trains_the_same_segmenter_and_another_seed_another(tmp_path):
    """Training crops and jitter follow the run's seed (torch's generator), so a run can be repeated exactly."""
    from drgan.segment import segment

    data = make_generated(tmp_path / "gen")

    def weights(name, seed):
        out = tmp_path / name
        segment(compose([*tiny_segment_overrides(data, tmp_path, out, "logger=none"), "trainer.max_epochs=2",
                         f"seed={seed}", "check_fraction=0"], config_name="segment"))  # fmt: skip
        state = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["state_dict"]
        return torch.cat([v.flatten().float() for v in state.values()])

    first = weights("a", 0)
    assert torch.equal(first, weights("b", 0))
    assert not torch.equal(first, weights("c", 1))


def test_contact_weight_auto_follows_the_generated_particles_polarity_and_arrangement(tmp_path):
    from drgan.segment import TrainingPairs, segment
    from drgan.segmenters.contacts import CONTACT_WEIGHT_AUTO, resolve_contact_weight
    from drgan.segmenters.module import load_segmenter

    assert compose([], config_name="segment").model.contact_weight == "auto"  # the default
    assert resolve_contact_weight("auto", "bright")[0] == CONTACT_WEIGHT_AUTO["bright"] == 10.0
    assert resolve_contact_weight("auto", "dark")[0] == CONTACT_WEIGHT_AUTO["dark"] == 0.0
    assert resolve_contact_weight("auto", None)[0] == 0.0  # real images: no polarity to go by
    assert resolve_contact_weight(3.0, "bright") == (3.0, "set")  # a number is kept whatever the data
    # bright particles: clustered (Clark-Evans < 1, agglomerates) keep the weight, random or regular ones do not
    assert resolve_contact_weight("auto", "bright", 0.54)[0] == 10.0
    assert resolve_contact_weight("auto", "bright", 1.0)[0] == 0.0
    weight, why = resolve_contact_weight("auto", "bright", 1.62)
    assert weight == 0.0 and "1.62" in why
    assert resolve_contact_weight("auto", "dark", 0.5)[0] == 0.0  # dark: 0 however clustered
    # the polarity is the generated set's (its manifest), none for real images or pairs without one
    bright = with_manifest(make_generated(tmp_path / "bright", n=4), "bright")
    dark = with_manifest(make_generated(tmp_path / "dark", n=4), "dark")
    assert TrainingPairs(data=str(bright)).polarity() == "bright"
    assert TrainingPairs(data=str(dark)).polarity() == "dark"
    assert TrainingPairs(data=str(make_generated(tmp_path / "bare", n=2))).polarity() is None
    assert TrainingPairs(real=str(tmp_path)).polarity() is None
    packed = with_manifest(make_generated(tmp_path / "packed", n=4), "bright", clark_evans=1.62)
    assert TrainingPairs(data=str(packed)).clark_evans() == 1.62
    assert TrainingPairs(data=str(bright)).clark_evans() is None  # a set from before manifests had it
    for data, weight in ((bright, 10.0), (dark, 0.0), (packed, 0.0)):
        out = tmp_path / f"run_{data.name}"
        cfg = compose([*tiny_segment_overrides(data, tmp_path, out, "logger=none"), "trainer.max_epochs=1",
                       "split_calibration=null"], config_name="segment")  # fmt: skip
        segment(cfg)
        trained = load_segmenter(out / "checkpoints" / "last.ckpt")
        assert trained.hparams.contact_weight == weight  # what it trained with
        recorded = json.loads((out / "metrics.json").read_text())["contact_weight"]
        assert recorded["value"] == weight and data.name in recorded["why"]


def test_segment_refuses_bad_data_before_writing(tmp_path):
    from drgan.segment import segment

    data = make_generated(tmp_path / "gen", n=2)
    Image.fromarray(np.full((32, 32), 3, np.uint8)).save(data / "masks" / "001.png")
    out = tmp_path / "run"
    with pytest.raises(DataError, match="unexpected values"):
        segment(compose([f"data={data}", f"out={out}", "logger=none"], config_name="segment"))
    assert not out.exists()


def test_segmentation_clis_take_data_and_model_on_the_command_line(tmp_path):
    """`python -m drgan.evaluate data=DIR model=CKPT` as a user types it: `data` and `model` are plain keys of the
    segmentation config root (no group of drgan.train's root is in the way); the missing folder is named."""
    import subprocess
    import sys

    missing = tmp_path / "nowhere"
    run = subprocess.run(
        [sys.executable, "-m", "drgan.evaluate", f"data={missing}", "model=a.ckpt", f"out={tmp_path / 'out'}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert run.returncode != 0
    assert f"data={missing}: no such folder" in run.stderr, run.stderr[-2000:]
    assert not (tmp_path / "out" / "results.json").exists()


def test_evaluate_takes_one_model_and_a_list(tmp_path):
    from drgan.evaluate import model_sources

    cfg = compose(["data=/d", "model=a.ckpt", "models=[b.ckpt,c.ckpt]"], config_name="evaluate")
    assert model_sources(cfg) == ["a.ckpt", "b.ckpt", "c.ckpt"]
    with pytest.raises(ConfigError, match="models='b.ckpt': expected a list"):
        model_sources(compose(["models=b.ckpt"], config_name="evaluate"))
    with pytest.raises(ConfigError, match="give model=CHECKPOINT"):
        model_sources(compose([], config_name="evaluate"))


# --- analysis ---------------------------------------------------------------------------------------------


def test_analyze_areas_equal_true_disc_areas(tmp_path):
    from drgan.analyze import AnalyzeSettings, analyze

    yy, xx = np.mgrid[:48, :48]
    labels = np.zeros((48, 48), np.int32)
    for k, (cy, cx, r) in enumerate([(10, 10, 5.0), (12, 34, 6.5), (34, 12, 3.2), (36, 36, 7.9)]):
        labels[(yy - cy) ** 2 + (xx - cx) ** 2 <= r * r] = k + 1
    folder = tmp_path / "images"
    folder.mkdir()
    Image.fromarray((disc_image(labels) * 255).astype(np.uint8)).save(folder / "img.png")
    cfg = compose(
        [f"images={folder}", f"out={tmp_path / 'out'}", "nm_per_px=2.0", "min_area_px=0", "wires=true"],
        config_name="analyze",
    )
    rows = analyze(AnalyzeSettings.from_config(cfg), predictor=lambda im: (labels > 0).astype(np.uint8))
    true_areas = sorted(int((labels == k).sum()) for k in range(1, labels.max() + 1))
    assert sorted(r["area_px"] for r in rows) == true_areas
    r = rows[0]
    assert r["area_nm2"] == pytest.approx(4 * r["area_px"]) and r["equivalent_diameter_nm"] == pytest.approx(
        2 * r["equivalent_diameter_px"]
    )
    table = list(csv.DictReader((tmp_path / "out" / "particles.csv").open()))
    assert len(table) == len(true_areas) and {"centroid_x", "bbox_min_row", "equivalent_diameter_px"} <= set(table[0])
    for name in ("histograms.png", "thickness_histogram.png", "thickness/img.png"):
        assert (tmp_path / "out" / name).is_file()


def test_local_thickness_of_a_strip():
    from drgan.analyze import local_thickness

    strip = np.zeros((30, 60), bool)
    strip[10:20, 5:55] = True
    t = local_thickness(strip)
    assert t[15, 30] == pytest.approx(10.0, abs=1.0) and t[0, 0] == 0
    assert (
        not local_thickness(np.zeros((5, 5), bool)).any() and np.isfinite(local_thickness(np.ones((5, 5), bool))).all()
    )


# --- messages that name the real cause ----------------------------------------------------------------------


def test_mask_of_another_size_is_reported_with_both_sizes_not_as_a_crop_problem(tmp_path):
    from drgan.evaluate import EvaluateSettings, evaluate

    # A TiO2-style crop [712, 768]: the image has 770 rows, its mask half of them.
    image, mask = np.full((770, 16), 0.5), np.zeros((385, 8), np.uint8)
    data = make_real(tmp_path / "real", {"a": image}, {"a": mask}, {"train": [], "test": ["a"]})
    cfg = compose([f"data={data}", f"out={tmp_path / 'out'}", "crop_rows=[712,768]"], config_name="evaluate")
    with pytest.raises(DataError) as caught:
        evaluate(
            EvaluateSettings.from_config(cfg, need_models=False),
            predictors={"x": lambda im: np.zeros(im.shape, np.uint8)},
        )
    message = str(caught.value)
    assert "a_m.tif: size 8 x 385 px (W x H) differs from its image" in message and "a.tif: 16 x 770 px" in message
    assert "or, without its info bar, 16 x 714 px" in message and "crop_rows" not in message
    # Same-size files with a crop that does not fit them: that one is a crop_rows problem, and says so.
    small = make_real(
        tmp_path / "small",
        {"a": np.full((20, 16), 0.5)},
        {"a": np.zeros((20, 16), np.uint8)},
        {"train": [], "test": ["a"]},
    )
    with pytest.raises(DataError, match=r"a\.tif: crop_rows .*inside its 20 rows"):
        evaluate(
            EvaluateSettings.from_config(
                compose([f"data={small}", f"out={tmp_path / 'out'}", "crop_rows=[712,768]"], config_name="evaluate"),
                need_models=False,
            ),
            predictors={"x": lambda im: np.zeros(im.shape, np.uint8)},
        )


def with_info_bar(image, rows=12):
    """The image above a black info bar with a line of white 'text' (as microscopes write them)."""
    bar = np.zeros((rows, image.shape[1]))
    bar[rows // 2, 2 : image.shape[1] // 3] = 1.0
    return np.concatenate([image, bar])


def test_info_bars_are_found_and_masks_published_without_them_are_accepted(tmp_path):
    """TSEM's layout: image with its info bar, mask already without it and named like the image (no _m)."""
    from drgan.data.images import info_bar_rows
    from drgan.segmenters.pairs import load_real

    rng = np.random.default_rng(0)
    field = np.clip(0.7 + rng.normal(0, 0.05, (48, 40)), 0.01, 0.99)
    field[10:20, 10:20] = 0.2  # one dark particle
    assert info_bar_rows(field) is None
    assert info_bar_rows(with_info_bar(field)) == (48, 60)
    assert info_bar_rows(with_info_bar(field[::-1])[::-1]) == (0, 12)  # a bar along the top
    mask = np.zeros((48, 40), np.uint8)
    mask[10:20, 10:20] = 255
    data = make_real(tmp_path / "tsem", {"a": with_info_bar(field)}, {}, {"train": ["a"], "test": []})
    tifffile.imwrite(data / "masks" / "a.tif", mask)  # TSEM names: ID.tif
    ((_, image, labels),) = load_real(data, ["a"])  # crop_rows auto, mask_suffix auto
    assert image.shape == (48, 40) and labels.max() == 1 and (labels > 0).sum() == 100
    with pytest.raises(DataError, match=r"a\.tif: size 40 x 48 px \(W x H\) differs from its image"):
        load_real(data, ["a"], crop_rows=None, mask_suffix="")  # no crop: the mask does not fit the whole image
    with pytest.raises(DataError, match=r"no mask for image id 'a' \(expected a_lbl\.tif"):
        load_real(data, ["a"], mask_suffix="_lbl")


@pytest.mark.parametrize("key, entry", [("real", "segment"), ("data", "segment"), ("data", "evaluate")])
def test_missing_dataset_folder_is_named_with_its_setting(key, entry, tmp_path):
    from drgan.evaluate import EvaluateSettings, evaluate
    from drgan.segment import segment

    missing = tmp_path / "nowhere"
    no_logger = ["logger=none"] if entry == "segment" else []
    cfg = compose([f"{key}={missing}", f"out={tmp_path / 'out'}", *no_logger], config_name=entry)
    run = (
        segment
        if entry == "segment"
        else lambda c: evaluate(EvaluateSettings.from_config(c, need_models=False), predictors={"x": lambda im: im})
    )
    with pytest.raises(DataError, match=rf"^{key}={missing}: no such folder \(expected a") as caught:
        run(cfg)
    assert "split.json: no such file" not in str(caught.value) and not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "setting, message",
    [
        ("loader.crop=abc", "loader.crop='abc': expected an integer >= 1"),
        ("loader.batch_size=0", "loader.batch_size=0: expected an integer >= 1"),
        ("loader.brightness=lots", "loader.brightness='lots': expected a finite number >= 0.0"),
        ("contour_px=1.5", "segment: contour_px=1.5: expected an integer >= 0"),
    ],
)
def test_segment_loader_settings_are_named_when_not_numbers(setting, message, tmp_path):
    from drgan.core.errors import ConfigError
    from drgan.segment import segment

    data = make_real(
        tmp_path / "real",
        {"a": np.full((16, 16), 0.5)},
        {"a": np.zeros((16, 16), np.uint8)},
        {"train": ["a"], "test": []},
    )
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=f"^{re.escape(message)}$"):
        segment(
            compose([f"real={data}", "crop_rows=null", f"out={out}", "logger=none", setting], config_name="segment")
        )
    assert not out.exists()


def test_segment_stops_when_val_loss_stops_improving_and_says_why(tmp_path, caplog):
    """min_delta larger than any change: epoch 1 sets the best, epoch 2 is no improvement, patience 1 stops
    there, far before max_epochs; metrics.json names the reason. Without early stopping it runs max_epochs."""
    from drgan.core.errors import ConfigError
    from drgan.segment import segment

    data = make_generated(tmp_path / "gen")

    def run(name, *extra):
        out = tmp_path / name
        segment(compose(tiny_segment_overrides(data, tmp_path, out, "logger=none", "name=tiny", *extra), "segment"))
        return json.loads((out / "metrics.json").read_text())

    with caplog.at_level(logging.WARNING, logger="drgan.segment"):
        record = run("stopped", "trainer.max_epochs=10", "early_stopping.patience=1", "early_stopping.min_delta=1e9")
    assert record["epoch"] == 2 and record["stop_reason"].startswith("patience: val/loss")
    # two validation epochs cannot show a settled score: the run says so (metrics.json and a warning)
    assert not record["settled"] and len(record["val_dsc_history"]) == 2
    assert "stopped before its validation score settled (only 2 validation epoch(s))" in caplog.text
    record = run("full", "trainer.max_epochs=3", "early_stopping=null")
    assert record["epoch"] == 3 and record["stop_reason"] == "max_epochs"
    with pytest.raises(ConfigError, match="early_stopping.monitor"):
        run("bad", "early_stopping.monitor=train/loss")


def test_real_images_are_sampled_by_their_area_and_generated_pairs_once_each(tmp_path):
    """An epoch of a few large real images is not a few crops: loader.samples_per_pair=auto draws round(area /
    crop^2) crops of each real image, and one of each generated pair (their number already sets the epoch)."""
    from drgan.segment import dataloaders, load_training_pairs
    from drgan.segmenters.pairs import CropDataset, crops_by_area

    labels = {i: disc_labels(64, seed=k) for k, i in enumerate(("a", "b", "c"))}
    real = make_real(
        tmp_path / "real",
        {i: disc_image(v) for i, v in labels.items()},
        {i: (v > 0) * 255 for i, v in labels.items()},
        {"train": ["a", "b", "c"], "test": []},
    )
    base = ["crop_rows=null", f"out={tmp_path / 'o'}", "loader.crop=16", "loader.batch_size=4", "val_fraction=0"]
    cfg = compose([f"real={real}", *base], config_name="segment")
    pairs = load_training_pairs(cfg)
    assert crops_by_area(pairs, 16) == [16, 16, 16]
    train, _, n_train, _ = dataloaders(cfg, pairs)
    assert n_train == 3 and len(train.dataset) == 48 and len(train) == 12
    # shrunk to a working scale (loader.working_px), the real images keep the crops of their original area
    from drgan.segmenters.pairs import rescale_pair

    shrunk = [rescale_pair(p, 0.5) for p in pairs]
    assert crops_by_area(shrunk, 16) == [4, 4, 4] and len(dataloaders(cfg, shrunk, scale=0.5)[0].dataset) == 48
    generated = compose([f"data={make_generated(tmp_path / 'gen', n=5, size=64)}", *base], config_name="segment")
    train, *_ = dataloaders(generated, load_training_pairs(generated))
    assert len(train.dataset) == 5
    fixed = compose([f"real={real}", *base, "loader.samples_per_pair=2"], config_name="segment")
    assert len(dataloaders(fixed, pairs)[0].dataset) == 6
    with pytest.raises(DataError, match="one count >= 1 per pair"):
        CropDataset(pairs, crop=16, augment=True, samples_per_pair=[1, 0, 1])


def test_a_validation_score_has_settled_only_when_the_last_epochs_stopped_raising_it():
    from drgan.segmenters.module import settled

    assert settled([0.2, 0.5, 0.6, 0.6, 0.605, 0.6])[0]  # +0.005 over the last 3 epochs
    rising, why = settled([0.2, 0.3, 0.32, 0.34, 0.36])
    assert not rising and "0.300 to 0.360" in why
    assert not settled([0.9, 0.9, 0.9])[0]  # too few epochs to tell


def test_split_core_opens_a_wide_neck_the_network_is_unsure_of():
    from drgan.metrics.instance_scores import binarize_and_label, match_instances
    from drgan.segmenters.inference import split_touching

    truth = _two_touching_discs(r=10.0, gap=7.0)  # a neck almost as wide as the discs
    probs = _probs_of(truth > 0)
    neck = (truth > 0) & (np.abs(np.arange(48) - 24 + 0.5) <= 1.5)[None, :]  # the 4 columns around the contact line
    probs[0][neck], probs[1][neck], probs[2][neck] = 0.3, 0.6, 0.1  # still particle by the argmax, but unsure
    argmax_core = binarize_and_label(split_touching(probs).astype(np.int64))
    assert argmax_core.max() == 1  # the distance transform alone sees one blob
    strict = binarize_and_label(split_touching(probs, split_core=0.7).astype(np.int64))
    m = match_instances(strict, truth, 0.5)
    assert m.tp == 2 and m.fp == 0 and m.fn == 0
    # the foreground (particle + contour > 0.5) is kept whole: the neck is cut by a line, not removed
    assert ((strict > 0) | (split_touching(probs, split_core=0.7) == 2)).sum() == (truth > 0).sum()
    from drgan.core.errors import ConfigError

    with pytest.raises(ConfigError, match="inference.split_core"):
        split_touching(probs, split_core=1.0)


def test_segment_yaml_and_the_settings_dataclasses_hold_the_same_defaults(tmp_path):
    """segment.yaml is the user's reference; LoaderSettings and TrainingPairs are the typed objects the stage reads:
    their defaults agree, so a key is one field (+ its YAML line), never two values that can drift apart."""
    import dataclasses

    from drgan.segment import LoaderSettings, TrainingPairs

    cfg = compose(["real=R"], config_name="segment")
    assert LoaderSettings.from_config(cfg) == LoaderSettings()
    pairs = TrainingPairs.from_config(cfg)
    assert pairs == dataclasses.replace(TrainingPairs(), real="R")
    generated = TrainingPairs.from_config(compose(["data=D", "contour_px=1.5"], config_name="segment"))
    assert generated == TrainingPairs(data="D")  # real-only keys are not read for generated pairs


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("depth", [0.5, 1.0, 2.0])
def test_h_maxima_cluster_by_cluster_are_those_of_the_whole_image(seed, depth):
    """The split's seeds, computed per cluster of the distance map (drgan.data.classical.watershed.cluster_h_maxima),
    equal skimage's h_maxima of the whole image: masked and smoothed distance maps of random touching discs, clusters
    at the image border included."""
    from scipy import ndimage as ndi
    from skimage.morphology import h_maxima

    from drgan.data.classical.watershed import cluster_h_maxima

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:96, :128]
    core = np.zeros((96, 128), bool)
    for _ in range(14):
        cy, cx, r = rng.uniform(-4, 100), rng.uniform(-4, 132), rng.uniform(3, 11)
        core |= (yy - cy) ** 2 + (xx - cx) ** 2 < r**2
    distance = ndi.gaussian_filter(ndi.distance_transform_edt(core), 1.0)
    for field in (distance, np.where(core, distance, 0.0)):
        expected = h_maxima(field, depth).astype(bool)
        assert expected.any()
        np.testing.assert_array_equal(cluster_h_maxima(field, depth), expected)
