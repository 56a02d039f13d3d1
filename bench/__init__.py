"""Benchmarks: run by hand or by `make bench`; figures go to BENCHMARKS.md, never into tests."""
