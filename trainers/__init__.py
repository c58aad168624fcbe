"""Fitting: the data-free subspace fitter (the paper's loss and schedule); SB3 agents on the envs (:mod:`.agents`)."""

from redsim.trainers.fit import FitConfig, FitResult, FitStopped, fit_subspace, subspace_loss

__all__ = ["FitConfig", "FitResult", "FitStopped", "fit_subspace", "subspace_loss"]
