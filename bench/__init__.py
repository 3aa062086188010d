"""Benchmarks: long runs kept out of the test suite. `python -m bench [--quick] [--only NAME] [--device cuda]`."""
