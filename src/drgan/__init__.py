"""drgan: DiffRenderGAN, realistic and exactly annotated synthetic microscopy of nanoparticles.

Importing drgan (or any of its modules) changes no global state: the entry points and `drgan.configs.compose` call
`drgan.configs.setup` (config schemas, shared groups, resolvers) before they compose a config.
"""

__version__ = "0.1.0"
