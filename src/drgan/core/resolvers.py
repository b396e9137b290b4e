"""The config resolvers of drgan's YAML files, registered by `drgan.launch.configs.setup` (every entry point and
`drgan.launch.configs.compose` calls it): ``${mul:a,b}`` and ``${mlflow_uri:default}``."""

from __future__ import annotations

import os

from omegaconf import OmegaConf

# The user's MLFLOW_TRACKING_URI as it was when drgan was imported (reading it changes nothing). Read once, because
# mlflow.set_tracking_uri (which Lightning's MLFlowLogger calls) overwrites the variable for the rest of the process:
# a second run in the same process (tests, in-process sweeps) would otherwise log into the first run's store.
_USER_TRACKING_URI = os.environ.get("MLFLOW_TRACKING_URI") or None


def user_tracking_uri() -> str | None:
    """The user's MLFLOW_TRACKING_URI as it was when drgan was imported, or None."""
    return _USER_TRACKING_URI


def register_resolvers() -> None:
    """Register drgan's resolvers with OmegaConf (idempotent)."""
    # `${mul:a,b}` lets size configs scale the material's typical particle size (e.g. std = 0.25 x size).
    if not OmegaConf.has_resolver("mul"):
        OmegaConf.register_new_resolver("mul", lambda a, b: float(a) * float(b))
    # `${mlflow_uri:default}`: the user's MLFLOW_TRACKING_URI, else default.
    if not OmegaConf.has_resolver("mlflow_uri"):
        OmegaConf.register_new_resolver("mlflow_uri", lambda default: user_tracking_uri() or default)
