"""How a stage starts: its Hydra app and help (`runtime`), its MLflow loggers (`loggers`), the composed and typed
configs (`configs`)."""
