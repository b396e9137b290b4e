"""Reading checkpoints without running code that a file brings along.

A ``.ckpt`` is a pickle inside a zip. Unpickled without restriction (``torch.load(weights_only=False)``), a file
can name any Python callable and have it called: a crafted checkpoint given as ``ckpt=``, ``init_from=``,
``ckpt_path=`` or ``model=`` would run its code before drgan could look at it. Every drgan load therefore goes
through ``torch.load(weights_only=True)``, whose unpickler rebuilds only tensors, containers and plain values
and refuses any other global *before* calling it.

drgan's checkpoints need nothing beyond that default allow-list (measured on torch 2.13 / Lightning 2.6 with
GANModule and segmenter checkpoints: ``last.ckpt``, ``best.ckpt``, top-k and weights-only epoch files, with and
without ``model.lr_decay``), because what drgan saves is kept plain: the model config is saved as plain
containers (``OmegaConf.to_container``), RNG states as tensors and lists (``callbacks.resume.rng_state``),
the learning-rate decay as its attributes (``LambdaLR`` stores a callable object's ``__dict__``). So there is
no allow-list here, and Lightning's own loads (``trainer.fit(ckpt_path=...)``, ``load_from_checkpoint``) get
``weights_only=True`` and the same default list; tests/test_checkpoint_io.py loads every kind of drgan
checkpoint with the bare ``torch.load(weights_only=True)``, so that content needing a class fails there
rather than at a user's resume. Keep it so: save plain values rather than allow-listing a class.

``load_checkpoint`` is the one reader; ``refusing_unsafe`` turns torch's refusal into drgan's message where
Lightning does the reading.
"""

from __future__ import annotations

import math
import pickle
import re
from collections.abc import Mapping
from contextlib import contextmanager
from pathlib import Path

import torch

from drgan.core.errors import ConfigError, DrganError

__all__ = ["add_entry", "load_checkpoint", "refusing_unsafe"]

# torch's refusal names what it refused after this prefix (e.g. "Unsupported global: GLOBAL getattr").
_REFUSED = re.compile(r"WeightsUnpickler error: (?P<what>[^\n]*?)(?: was not an allowed global by default.*)?$", re.M)


def _refusal(error: pickle.UnpicklingError, what: str, path, kind: type[DrganError]) -> DrganError:
    found = _REFUSED.search(str(error))
    detail = found["what"].strip() if found else str(error).splitlines()[0]
    return kind(
        f"{what}={path}: refused: the file holds Python objects that could run code when loaded ({detail}); "
        "drgan checkpoints hold only tensors and plain values, so this file was not written by drgan or was altered. "
        "Nothing in it was run"
    )


@contextmanager
def refusing_unsafe(what: str, path, error: type[DrganError] = ConfigError):
    """Inside: a load that torch's weights-only unpickler refuses raises ``error`` naming the setting and file."""
    try:
        yield
    except pickle.UnpicklingError as refused:
        raise _refusal(refused, what, path, error) from None


def load_checkpoint(
    path, what: str, *, expected: str = "a .ckpt written by drgan", error: type[DrganError] = ConfigError
) -> dict:
    """The checkpoint dict at ``path`` (on the CPU), loaded with ``weights_only=True``.

    ``what`` names the setting that gave the path (``ckpt``, ``init_from``, ``ckpt_path``, ``model``) and
    ``expected`` what it should hold; both appear in the ``error`` raised for a missing file, one that holds
    code (refused before any of it runs), a damaged or non-PyTorch file, and one that is not a Lightning
    checkpoint (a dict with a ``state_dict``). What kind of drgan checkpoint it is, is the caller's check.
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{what}={path}: no such checkpoint file ({expected})")
    with refusing_unsafe(what, path, error):
        try:
            checkpoint = torch.load(path, map_location="cpu", weights_only=True)
        except pickle.UnpicklingError:
            raise
        except Exception as damaged:  # truncated zip, text, an empty file: RuntimeError, KeyError, EOFError
            raise error(
                f"{what}={path}: not a readable PyTorch checkpoint (damaged, truncated or another kind of file: "
                f"{type(damaged).__name__}: {str(damaged).splitlines()[0] if str(damaged) else 'no detail'}); expected {expected}"
            ) from None
    if not isinstance(checkpoint, dict) or not isinstance(checkpoint.get("state_dict"), dict):
        raise error(
            f"{what}={path}: a PyTorch file but not a Lightning checkpoint (no state_dict); expected {expected}"
        )
    return checkpoint


def positive_entry(checkpoint: Mapping, key: str) -> float | None:
    """A checkpoint's entry ``key`` as a positive finite number, or None (absent, or anything else: a bool, a string,
    zero, a negative number, inf or nan)."""
    entry = checkpoint.get(key)
    if isinstance(entry, bool) or not isinstance(entry, (int, float)) or not 0 < entry < math.inf:
        return None
    return float(entry)


def add_entry(path, key: str, value, what: str = "ckpt") -> None:
    """Store ``value`` (plain values only, as everything drgan saves) under ``key`` in the checkpoint at ``path``,
    written whole to a temporary file and renamed into place: a kill leaves the old checkpoint or the new one."""
    path = Path(path)
    checkpoint = load_checkpoint(path, what)
    checkpoint[key] = value
    tmp = path.with_name(f".{path.name}.partial")
    torch.save(checkpoint, tmp)
    tmp.replace(path)
