"""Atomic file writes: long jobs never leave half-written files (write to a temporary name, then rename); and the
CSV tables drgan writes read back."""

from __future__ import annotations

import io
import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np


def _umask() -> int:
    """The process's umask (read by setting it and setting it back: the only way the OS gives it)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; on success it replaces ``path`` in one rename, with the mode a file
    created there directly would have (0666 less the umask: readable by a colleague or a tracking server on a shared
    file system; mkstemp's own temporary files are 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_with(path: str | os.PathLike, write) -> None:
    """Call ``write(binary_file)`` on a temporary file, then rename it to ``path``.

    A file object (not a name) suits np.savez (which would append ".npz" to a name) and PIL's save.
    """
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    write_with(path, lambda handle: handle.write(data))


def write_json(path: str | os.PathLike, obj) -> None:
    write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode())


def write_png(path: str | os.PathLike, array: np.ndarray) -> None:
    """Grey PNG: float images in [0, 1] -> 8 bit; integer arrays kept (uint8, or uint16 for ids > 255)."""
    from PIL import Image

    array = np.asarray(array)
    if np.issubdtype(array.dtype, np.floating):
        array = np.round(np.clip(array, 0.0, 1.0) * 255.0).astype(np.uint8)
    elif array.max(initial=0) > 255:
        if array.max() > 65535:
            raise ValueError(f"{path}: ids up to 65535 fit a 16-bit PNG, got {array.max()}")
        array = array.astype(np.uint16)
    else:
        array = array.astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    write_bytes(path, buffer.getvalue())


def figure_png(draw) -> bytes:
    """PNG bytes of the matplotlib figure that ``draw(plt)`` returns (Agg backend; the figure is closed)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = draw(plt)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def read_csv(path: str | os.PathLike) -> tuple[list[dict], list[str]]:
    """A CSV table drgan wrote (header row first): its rows as dicts of strings and its columns; ([], []) when there
    is no file."""
    import csv

    path = Path(path)
    if not path.is_file():
        return [], []
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        return list(reader), list(reader.fieldnames or [])
