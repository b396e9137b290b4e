"""Training callbacks: per-epoch FID/KID, best-epoch selection (low FID, broad parameters), plots, progress bar."""

from drgan.callbacks.best_epoch import BestEpochCallback, parameter_spread, select_best
from drgan.callbacks.early_stop import FIDEarlyStopping, should_stop, stop_reason
from drgan.callbacks.fid import FIDCallback, RandomProjectionFeatures
from drgan.callbacks.grey_start import GreyStart
from drgan.callbacks.progress_bar import StepProgress, TrainingProgressBar
from drgan.callbacks.resume import ResumeCheckpoint
from drgan.callbacks.visuals import ParameterHistogramCallback, SampleGridCallback

__all__ = [
    "FIDCallback",
    "FIDEarlyStopping",
    "GreyStart",
    "should_stop",
    "stop_reason",
    "ResumeCheckpoint",
    "RandomProjectionFeatures",
    "BestEpochCallback",
    "parameter_spread",
    "select_best",
    "ParameterHistogramCallback",
    "SampleGridCallback",
    "StepProgress",
    "TrainingProgressBar",
]
