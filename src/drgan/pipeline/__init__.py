"""The pipeline command, from a folder of images to particle numbers: its overview is drgan.pipeline.runner's
(`python -m drgan.pipeline --help` prints it); its stages are declared in drgan.pipeline.stage_table."""

from drgan.pipeline import stage_table
from drgan.pipeline.runner import main, run
from drgan.pipeline.settings import Settings, parse_settings

__all__ = ["STAGES", "Settings", "main", "parse_settings", "run"]


def __getattr__(name: str):
    """``STAGES``: the stages' names in order, read from stage_table.PIPELINE at each read."""
    if name == "STAGES":
        return stage_table.STAGES
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
