"""Mitsuba/Dr.Jit start-up: find a usable libLLVM and pick the rendering variant.

Import this module (or anything under ``drgan.scene``) instead of importing ``mitsuba`` directly:
Dr.Jit's CPU backend reads ``DRJIT_LIBLLVM_PATH`` once, when Mitsuba is first imported, and the
libLLVM versions Debian ships by default (14, 15) crash at the first render. We look for LLVM >= 16
and point Dr.Jit at it before the import.
"""

from __future__ import annotations

import ctypes.util
import glob
import logging
import os
import re
from functools import cache

from drgan.core.errors import ConfigError

log = logging.getLogger(__name__)

MIN_LLVM_MAJOR = 16
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)


def _llvm_major(path: str) -> int | None:
    match = re.search(r"(?:LLVM|llvm)-?(\d+)", os.path.basename(path)) or re.search(r"llvm-(\d+)", path)
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """Path of the newest libLLVM with major version >= 16 on this machine, or None."""
    candidates = {p for pattern in _LLVM_GLOBS for p in glob.glob(pattern)}
    found = ctypes.util.find_library("LLVM")
    if found and os.path.isabs(found):
        candidates.add(found)
    versioned = [(_llvm_major(p), p) for p in candidates]
    usable = [(major, p) for major, p in versioned if major is not None and major >= MIN_LLVM_MAJOR]
    if not usable:
        return None
    # Newest major first; among equals prefer the shortest name (the plain .so symlink).
    usable.sort(key=lambda mp: (-mp[0], len(mp[1])))
    return usable[0][1]


def configure_llvm() -> str | None:
    """Set DRJIT_LIBLLVM_PATH (when unset) so Dr.Jit's CPU backend loads a working libLLVM."""
    current = os.environ.get("DRJIT_LIBLLVM_PATH")
    if current:
        return current
    path = find_libllvm()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
        log.debug("DRJIT_LIBLLVM_PATH=%s", path)
    return path


configure_llvm()

import drjit as dr  # noqa: E402  (must follow configure_llvm)
import mitsuba as mi  # noqa: E402

VARIANT_CHOICES = ("auto", "llvm_ad_rgb", "llvm_ad_mono", "cuda_ad_rgb", "cuda_ad_mono")


@cache
def cuda_usable() -> bool:
    """True when Mitsuba's CUDA variant can be set on this machine (a driver and a GPU are present)."""
    if "cuda_ad_rgb" not in mi.variants():
        return False
    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # pragma: no cover - depends on the driver stack
        return False


def resolve_variant(requested: str = "auto") -> str:
    """``auto`` -> ``cuda_ad_rgb`` when a GPU is usable, ``llvm_ad_rgb`` otherwise."""
    if requested not in VARIANT_CHOICES:
        raise ConfigError(f"renderer.variant={requested!r}: expected one of {', '.join(VARIANT_CHOICES)}")
    if requested == "auto":
        return "cuda_ad_rgb" if cuda_usable() else "llvm_ad_rgb"
    if requested.startswith("cuda") and not cuda_usable():
        raise ConfigError(f"renderer.variant={requested!r}: no usable CUDA GPU here; use 'auto' or an llvm_* variant")
    if requested.startswith("llvm") and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        raise ConfigError(
            f"renderer.variant={requested!r}: no libLLVM >= {MIN_LLVM_MAJOR} found; "
            "install one (Debian: apt-get install libllvm19) or set DRJIT_LIBLLVM_PATH"
        )
    return requested


THREADS_ENV = "DRGAN_RENDER_THREADS"  # Dr.Jit CPU threads; unset: one per core


def use_variant(requested: str = "auto") -> str:
    """Set Mitsuba's variant (once per process; switching later invalidates built scenes)."""
    variant = resolve_variant(requested)
    if mi.variant() != variant:
        mi.set_variant(variant)
    threads = os.environ.get(THREADS_ENV)
    if threads and variant.startswith("llvm"):
        # The adjoint pass sums gradients from many threads in no fixed order, so two runs with the same seeds
        # differ in the last bits (~1e-6 in the weights after a few steps). One thread makes runs bitwise
        # repeatable (the fault tests compare resumed and uninterrupted runs bitwise), at the cost of speed.
        if not threads.isdigit() or int(threads) < 1:
            raise ValueError(f"{THREADS_ENV}={threads!r}: expected a positive integer (Dr.Jit CPU threads)")
        dr.set_thread_count(int(threads))
    return variant
