"""Decluttering benchmark, baselines, ablations and reports. Imports `sgjax`, `envs` and `train`."""
