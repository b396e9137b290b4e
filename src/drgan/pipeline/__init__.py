"""The pipeline command, from a folder of images to particle numbers: its overview is drgan.pipeline.runner's
(`python -m drgan.pipeline --help` prints it)."""

from drgan.pipeline.runner import main, run
from drgan.pipeline.settings import STAGES, Settings, parse_settings

__all__ = ["STAGES", "Settings", "main", "parse_settings", "run"]
