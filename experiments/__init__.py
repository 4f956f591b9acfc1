"""Experiments that reproduce the thesis's results in simulation (``python -m experiments.…``)."""
