"""Where the bake's chunks run beyond this process: a Dask cluster (the local thread pool is core/base/threads, which the estimators use)."""
