"""Real images: reading, splits, and mining of training and background patches."""

from drgan.data.classical import SegmentParams, segment_particles
from drgan.data.images import list_images, read_grey, read_split
from drgan.data.patches import PatchSet, contact_sheet, count_particles, dihedral_augment, mine_patches

__all__ = [
    "PatchSet",
    "SegmentParams",
    "contact_sheet",
    "count_particles",
    "dihedral_augment",
    "list_images",
    "mine_patches",
    "read_grey",
    "read_split",
    "segment_particles",
]
