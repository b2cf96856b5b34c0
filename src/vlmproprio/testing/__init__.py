"""Test helpers that ship with the package so tests, benchmarks and users can share them (no model, no network)."""
