"""Benchmarks: ``python -m prtt_addon.bench <bake|...>`` print numbers (see docs/benchmarks.md)."""
