"""Benchmarks: ``python -m prtt_addon.dev.bench <bake|...>`` print numbers (see docs/benchmarks.md)."""
