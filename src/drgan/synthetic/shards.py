"""Shards of one dataset folder: who writes which item, and when the dataset is complete.

``shard=i/k`` owns the synthetic indices with index % k == i; all shards write into one folder. The dataset is
the first n kept indices (as in a single process), so it is complete once indices 0..j are all done and n of
them are kept (``dataset_cutoff``); kept indices beyond j (rendered by a shard that could not yet know) stay on
disk but are not in the manifest.
"""

from __future__ import annotations

from dataclasses import dataclass

from drgan.core.errors import ConfigError
from drgan.synthetic.folder import BG, PARTIAL_RECORD, PBG, syn_index


@dataclass(frozen=True)
class Shard:
    index: int
    count: int

    @classmethod
    def parse(cls, text) -> Shard:
        """ "i/k" with 0 <= i < k; None or "" is the whole range (0/1)."""
        if text in (None, "", "null"):
            return cls(0, 1)
        parts = str(text).split("/")
        try:
            i, k = (int(p) for p in parts)
        except ValueError:
            i, k = -1, 0
        if len(parts) != 2 or k < 1 or not 0 <= i < k:
            raise ConfigError(f"shard={text!r}: expected 'i/k' with integers 0 <= i < k, e.g. shard=0/4")
        return cls(i, k)

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    def owns_index(self, index: int) -> bool:
        return index % self.count == self.index


def shard_manifest_name(shard: Shard) -> str:
    return f"manifest_shard_{shard.index}.json"


def owned_by(item: str, shard: Shard) -> bool:
    """Whether ``shard`` is the only writer of ``item`` (a file stem): its synthetic indices, the backgrounds and
    partial backgrounds (and their record) for shard 0, manifest_shard_i for shard i; manifest.json and config.json
    only when there is one process."""
    index = syn_index(item)
    if index is not None:
        return shard.owns_index(index)
    if item.startswith((BG + "_", PBG + "_")) or item == PARTIAL_RECORD.removesuffix(".json"):
        return shard.index == 0
    if item.startswith("manifest_shard_"):
        return item == f"manifest_shard_{shard.index}"
    return shard.count == 1


def kept_below(outcomes: dict[int, bool], j: int) -> int:
    """How many indices below j are known to be kept (``outcomes``: index -> kept, DatasetFolder.outcomes)."""
    return sum(1 for i, k in outcomes.items() if k and i < j)


def dataset_cutoff(outcomes: dict[int, bool], n: int) -> tuple[int | None, int]:
    """(index of the n-th kept index if indices 0..it are all done, else None; first missing index)."""
    kept, i = 0, 0
    while i in outcomes:
        kept += outcomes[i]
        if kept >= n:
            return i, i + 1
        i += 1
    return None, i
