"""drgan: DiffRenderGAN, realistic and exactly annotated synthetic microscopy of nanoparticles.

The stages, in the order a folder of unannotated images goes through them (each ``python -m drgan.STAGE`` or
``drgan STAGE``; ``drgan.pipeline`` runs them all):

- ``profile``: read the images, propose a material (its helpers: ``drgan.profiling``);
- ``train``: the GAN, a small network feeding a differentiable renderer;
- ``generate``: image/mask pairs from the best epoch;
- ``segment``: a segmenter trained on them;
- ``analyze``: particle sizes and counts of the user's images; ``evaluate`` scores against annotations.

Beside them: ``render``, ``realism``, ``meshes``, ``export_nnunet``, ``import_official``, ``view``, ``mlflow_ui``.
What the stages share lives in packages: ``launch`` (start-up, configs, loggers), ``core`` (errors, files,
checkpoints, the renderer backend), and the domain packages ``scene``, ``models``, ``data``, ``metrics``,
``synthetic``, ``segmenters``, ``callbacks``.

Importing drgan (or any of its modules) changes no global state: the entry points and `drgan.launch.configs.compose`
call `drgan.launch.configs.setup` (config schemas, shared groups, resolvers) before they compose a config.
"""

__version__ = "0.1.0"
