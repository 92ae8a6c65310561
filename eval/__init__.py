"""Decluttering benchmark, baselines, ablations and reports. Imports `sgjax` and `envs` (never `train`)."""
