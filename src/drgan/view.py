"""`drgan view RUN` (or `python -m drgan.view RUN`): a pipeline run folder, or an analyze folder, in napari: each
image with its particles as a labels layer, the particle table as that layer's features (drgan's napari reader,
drgan/napari.yaml). Needs napari: `pip install "drgan[napari]"` (napari is imported here only)."""

from __future__ import annotations

import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    from drgan.data.napari_reader import analyze_folder

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    run = argv[0]
    if analyze_folder(run) is None:
        print(f"error: view: {run}: not a drgan run or analyze folder (expected particles.csv and labels/ in it or in "
              "its analyze/; analyze writes them)", file=sys.stderr)  # fmt: skip
        return 1
    try:
        import napari
    except ImportError:
        print('error: view: napari is not installed; pip install "drgan[napari]" (or pip install "napari[all]"), '
              "or open the run's labels/*.tif and rois/*.zip in Fiji", file=sys.stderr)  # fmt: skip
        return 1
    viewer = napari.Viewer(title=f"drgan: {run}")
    viewer.open(run, plugin="drgan")
    napari.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
