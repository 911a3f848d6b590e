"""Benchmarks: ``python -m rtsplat.bench.raster``."""
