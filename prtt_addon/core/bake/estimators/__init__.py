"""The bake's estimators and kernels: transfer, bounces, sampling, ray tracing, denoising."""
