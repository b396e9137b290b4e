"""Config groups shared by every entry point: paths (where runs and data live), logger (MLflow or none)."""
