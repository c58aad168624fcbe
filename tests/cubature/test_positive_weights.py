"""Cubature selection keeps only elements NNLS weighs above zero: a zero-weight element costs time, adds nothing."""

from __future__ import annotations

import torch

from redsim.cubature.fit import greedy_nnls


def test_no_kept_element_has_weight_zero() -> None:
    # 100 candidate elements of 30 rows, asked for 40: NNLS refits more columns than it can use (its solution keeps at
    # most as many as there are rows) and zeroes some, which must be dropped rather than kept with weight 0
    g = torch.Generator().manual_seed(0)
    train = torch.randn(30, 100, generator=g, dtype=torch.float64) + 0.3
    test = torch.randn(6, 100, generator=g, dtype=torch.float64)
    train_norm = float(torch.linalg.vector_norm(train.sum(1)))
    test_norm = float(torch.linalg.vector_norm(test.sum(1)))
    kept, weights, history = greedy_nnls(train, test, train_norm, test_norm, elements=40, tol=None)
    assert kept.numel() == weights.numel() == history[-1][0]
    assert kept.numel() <= train.shape[0]
    assert bool((weights > 0.0).all()), weights
    assert len(set(kept.tolist())) == kept.numel()
    # the weights are the NNLS fit on the kept columns: the row sums are matched no worse than by the first element
    residual = torch.linalg.vector_norm(train[:, kept] @ weights - train.sum(1)) / train_norm
    assert float(residual) == history[-1][1] < 1e-12
    assert history[-1][1] <= history[0][1]
