"""Labelling (grasp trials in simulation) and E-RNet training. Imports `sgjax` and `envs`."""
