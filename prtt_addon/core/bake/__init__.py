"""The bake: settings, chunk planning and sampling, transfer and bounce estimators, ray tracing, the stage runner."""
