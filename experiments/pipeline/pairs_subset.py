"""The first N rendered pairs of a generated set as a set of their own (symlinks and a filtered manifest.json), with
every background window: what `generate n=N` would have written, since each pair is rendered from its own index's
seed. For the segmenter's pairs curve (issue 68): how many pairs a segmenter needs.

    python experiments/pipeline/pairs_subset.py runs/pipeline/cej/generate 500 /work/tmp/cej_500
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("source", type=Path)
    ap.add_argument("n", type=int)
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    manifest = json.loads((args.source / "manifest.json").read_text())
    synthetic = [e for e in manifest["entries"] if e["kind"] == "synthetic"]
    if len(synthetic) < args.n:
        raise SystemExit(f"{args.source}: {len(synthetic)} rendered pairs, fewer than {args.n}")
    kept = synthetic[: args.n] + [e for e in manifest["entries"] if e["kind"] != "synthetic"]
    for entry in kept:
        for relative in entry["files"].values():
            target = args.out / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            if not target.exists():
                os.symlink((args.source / relative).resolve(), target)
    for name in os.listdir(args.source):  # the set's own files (noise and edge checks, config)
        path = args.source / name
        if path.is_file() and name != "manifest.json" and not (args.out / name).exists():
            os.symlink(path.resolve(), args.out / name)
    counts = {**manifest["counts"], "synthetic": args.n, "kept": args.n}
    (args.out / "manifest.json").write_text(json.dumps({**manifest, "entries": kept, "counts": counts}, indent=1))
    print(f"{args.out}: {args.n} of {len(synthetic)} pairs, {len(kept) - args.n} background windows")


if __name__ == "__main__":
    main()
