"""Benchmarks: `python -m benchmarks.NAME [--json]`, each against a baseline in the same run."""
