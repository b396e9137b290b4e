"""Command-line spelling of the segmentation entry points.

`conf/` holds config groups named `data` and `model` (for drgan.train), so Hydra would read `data=DIR`
or `model=CKPT` as a group choice and refuse it. The entry points accept those short forms by renaming
them before Hydra parses the command line: `data=X` -> `data_dir=X`, and every `model=X` (repeatable)
-> one `models=[X,Y,...]` list (or `ckpt=X` where one model is expected).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable


def _quote(value: str) -> str:
    return (
        value if value.replace("/", "").replace(".", "").replace("_", "").replace("-", "").isalnum() else f"'{value}'"
    )


def rewrite_argv(argv: list[str], *, many_models: bool) -> list[str]:
    out, models = [], []
    for arg in argv:
        key, eq, value = arg.partition("=")
        if eq and key == "data":
            out.append(f"data_dir={value}")
        elif eq and key == "model":
            models.append(value)
        else:
            out.append(arg)
    if models:
        if many_models:
            out.append("models=[" + ",".join(_quote(m) for m in models) + "]")
        else:
            out.append(f"ckpt={models[-1]}")
    return out


def run_cli(main: Callable[[], object], *, many_models: bool) -> None:
    """The ``__main__`` of evaluate, segment and analyze: short errors, rewritten argv, then the Hydra main."""
    os.environ.setdefault("HYDRA_FULL_ERROR", "0")
    sys.argv = [sys.argv[0], *rewrite_argv(sys.argv[1:], many_models=many_models)]
    main()
