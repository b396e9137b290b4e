"""drgan: DiffRenderGAN, realistic and exactly annotated synthetic microscopy of nanoparticles."""

import warnings

__version__ = "0.1.0"

# The configs put ./drgan_conf (users' own materials, e.g. from `python -m drgan.profile`) on Hydra's search path;
# Hydra warns on every run in a folder that has none, which is the usual case and nothing to act on.
warnings.filterwarnings("ignore", message=r"provider=hydra\.searchpath in main, path=drgan_conf is not available")

from drgan import resolvers  # noqa: E402,F401  (${mul:}, ${mlflow_uri:}: every config composes with them)
from drgan.configs import register_configs  # noqa: E402  (schemas and shared groups, before anything composes)

register_configs()
