"""Gymnasium environments over latent subspaces (`RedSim/...-v0`); they arrive with the subspace fitter."""
