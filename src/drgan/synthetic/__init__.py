"""A synthetic segmentation dataset on disk: written by drgan.generate, read by drgan.export_nnunet and
drgan.segment. The one place that knows the folder layout.

- ``folder``: item ids (``syn_000123``, ``bg_0000``), their files (images/, masks/, labels/, meta/, dropped/),
  the record that marks an item done, clean-up after an interrupted run, config.json (the fixed settings);
- ``manifest``: manifest.json (and a shard's manifest_shard_I.json) written atomically once the dataset is
  complete; ``read_manifest`` checks a folder and names it when it is not a drgan dataset;
- ``shards``: which shard writes which item, and when the first n kept indices are all done;
- ``generation_settings``: a generation run's settings, checked against the checkpoint; ``source``: that checkpoint;
- ``backgrounds``: the real background patches added with all-zero masks, and the partial backgrounds (real
  windows with particles, masked ``IGNORE`` = 255) that fill up when there are too few.
"""

from drgan.synthetic.folder import (
    BACKGROUND,
    IGNORE,
    PARTIAL_BACKGROUND,
    SYNTHETIC,
    DatasetFolder,
    Entry,
    bg_id,
    item_files,
    pbg_id,
    syn_id,
)
from drgan.synthetic.manifest import (
    GENERATED_DATASET,
    check_files,
    is_generated,
    manifest_entries,
    manifest_pixel_scale,
    read_manifest,
    unlisted_items,
    write_manifest,
    write_shard_manifest,
)
from drgan.synthetic.shards import Shard, dataset_cutoff, kept_below, owned_by

__all__ = [
    "BACKGROUND", "GENERATED_DATASET", "IGNORE", "PARTIAL_BACKGROUND", "SYNTHETIC", "DatasetFolder", "Entry", "Shard",
    "bg_id", "check_files", "dataset_cutoff", "is_generated", "item_files", "kept_below", "manifest_entries",
    "manifest_pixel_scale", "owned_by", "pbg_id", "read_manifest", "syn_id", "unlisted_items", "write_manifest", "write_shard_manifest",
]  # fmt: skip
