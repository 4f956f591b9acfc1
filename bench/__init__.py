"""Benchmarks: ``python -m bench [SECTION …]`` prints figures and ratios."""
