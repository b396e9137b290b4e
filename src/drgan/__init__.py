"""drgan: DiffRenderGAN, realistic and exactly annotated synthetic microscopy of nanoparticles."""

__version__ = "0.1.0"
