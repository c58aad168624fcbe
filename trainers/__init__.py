"""Subspace fitting and agent training helpers; they build on the engine in :mod:`redsim`."""
