"""Weighted L2-regularised logistic regression (Newton / IRLS), for fitting the floor
model's cue weights offline. Deterministic and dependency-free."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def fit_logistic_regression(
    features: NDArray[np.float64],
    targets: NDArray[np.float64],
    sample_weight: NDArray[np.float64],
    *,
    l2: float = 1e-2,
    iterations: int = 50,
) -> NDArray[np.float64]:
    """Fit ``p(y=1 | x) = sigmoid(x @ w)``.

    Parameters
    ----------
    features : (m, d) float64
        The last column must be the constant 1 (the intercept); it is not standardised
        and not penalised less than the others.
    targets : (m,) float64 in {0, 1}
    sample_weight : (m,) float64 >= 0
    l2 : float
        Ridge penalty on the standardised coefficients, relative to the total weight.
    iterations : int
        Newton steps (the problem is convex and smooth; 50 is far past convergence).

    Returns
    -------
    (d,) float64 weights for the raw (unstandardised) features.
    """
    if features.ndim != 2 or features.shape[0] != targets.shape[0] != sample_weight.shape[0]:
        raise ValueError("features, targets and sample_weight must agree on the sample count")
    if not np.allclose(features[:, -1], 1.0):
        raise ValueError("the last feature column must be the constant 1 (intercept)")
    center = features.mean(axis=0)
    scale = features.std(axis=0) + 1e-9
    center[-1], scale[-1] = 0.0, 1.0
    x = (features - center) / scale
    beta = np.zeros(features.shape[1])
    total = float(sample_weight.sum())
    ridge = l2 * total * np.eye(beta.size)
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-(x @ beta)))
        gradient = x.T @ (sample_weight * (p - targets)) + l2 * total * beta
        hessian = (x * (sample_weight * p * (1.0 - p))[:, None]).T @ x + ridge
        beta -= np.linalg.solve(hessian, gradient)
    weights: NDArray[np.float64] = beta / scale
    weights[-1] = beta[-1] - float((center[:-1] * beta[:-1] / scale[:-1]).sum())
    return weights
