"""benchmark/ is a package so that its tests can share benchmark/metrics.py."""
