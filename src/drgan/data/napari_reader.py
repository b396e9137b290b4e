"""napari's reader for drgan's results (the npe2 contract; the manifest is drgan/napari.yaml): a pipeline run folder
(its analyze/ inside) or an analyze folder opens as, per image, the image and its particles as a labels layer named
``ID particles``, whose features are that image's rows of particles.csv (napari shows a particle's row under the
cursor), in nm where the label TIFF carries the pixel size. Nothing of napari is imported here: the reader returns
layer data tuples, as the contract asks."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from drgan.core.io import read_csv

LayerData = tuple  # (data, keyword arguments, layer type)


def analyze_folder(path: str | Path) -> Path | None:
    """The analyze folder of ``path`` (itself, or a pipeline run's analyze/), None when it is neither."""
    path = Path(path)
    for folder in (path, path / "analyze"):
        if (folder / "particles.csv").is_file() and (folder / "labels").is_dir():
            return folder
    return None


def get_reader(path: str | list[str]) -> Callable[[str], list[LayerData]] | None:
    """The reader for ``path`` if it is a drgan run or analyze folder, else None (napari tries another plugin)."""
    if isinstance(path, list):
        path = path[0] if len(path) == 1 else None
    return read_run if path is not None and analyze_folder(path) is not None else None


def read_run(path: str | list[str]) -> list[LayerData]:
    from drgan.data.imagej import read_label_tiff

    folder = analyze_folder(path[0] if isinstance(path, list) else path)
    summary = json.loads((folder / "summary.json").read_text()) if (folder / "summary.json").is_file() else {}
    images_dir = Path(summary["images_dir"]) if summary.get("images_dir") else None
    rows = read_csv(folder / "particles.csv")[0]
    layers: list[LayerData] = []
    for tif in sorted((folder / "labels").glob("*.tif")):
        image_id = tif.stem
        labels, nm = read_label_tiff(tif)
        scale = (nm, nm) if nm else (1.0, 1.0)
        image = _image(images_dir, image_id)
        if image is not None:
            layers.append((image, {"name": image_id, "scale": scale}, "image"))
        mine = [r for r in rows if r.get("image") == image_id]
        features = {"index": [int(r["id"]) for r in mine]}
        for key in mine[0] if mine else {}:
            if key not in ("id", "image"):
                features[key] = [_value(r[key]) for r in mine]
        layers.append((labels, {"name": f"{image_id} particles", "scale": scale, "features": features,
                                "opacity": 0.5}, "labels"))  # fmt: skip
    return layers


def _image(images_dir: Path | None, image_id: str):
    if images_dir is None or not images_dir.is_dir():
        return None
    from drgan.data.images import list_images, read_grey

    found = [p for p in list_images(images_dir) if p.stem == image_id]
    return read_grey(found[0]) if found else None


def _value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"True": True, "False": False}.get(text, text)
