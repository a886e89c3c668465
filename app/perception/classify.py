"""Stage 5: the thesis's normalised 7-feature SSD classifier of superpixels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SsdClassification:
    """Result of `ssd_classify`.

    Attributes
    ----------
    ssd : (n,) float32
        Normalised sum of squared differences of each superpixel's features to the mean
        of the safe-zone superpixels.
    threshold : float
        The largest SSD among the safe-zone superpixels (the thesis's threshold).
    is_floor : (n,) bool
        ``ssd <= threshold``.
    """

    ssd: NDArray[np.float32]
    threshold: float
    is_floor: NDArray[np.bool_]


def ssd_classify(
    features: NDArray[np.float32],
    training: NDArray[np.bool_],
    *,
    threshold_quantile: float = 1.0,
) -> SsdClassification:
    """Classify superpixels as floor by a normalised SSD to the safe-zone mean.

    Each of the features (columns) is divided by its standard deviation over all
    superpixels of the frame, so that colour (Lab units) and shape (pixels) weigh alike:
    that is the "normalised" in the thesis's normalised SSD. The mean of the training
    (safe-zone) superpixels is subtracted and the squares summed. The threshold is the
    maximum SSD over the training set (``threshold_quantile=1``), or a quantile of it for
    a threshold robust to a non-floor superpixel in the safe zone.

    Parameters
    ----------
    features : (n, d) float32
        For the thesis d = 7: width, height, diagonal, L, a, b, area
        (`SuperpixelFeatures.thesis_vector`).
    training : (n,) bool
        Superpixels assumed to be floor (those intersecting the safe zone).
    threshold_quantile : float in (0, 1]

    Returns
    -------
    SsdClassification

    Examples
    --------
    >>> x = np.array([[0.0], [1.0], [10.0]], np.float32)
    >>> ssd_classify(x, np.array([True, True, False])).is_floor.tolist()
    [True, True, False]
    """
    if features.ndim != 2 or features.shape[0] != training.shape[0]:
        raise ValueError(f"features {features.shape} and training {training.shape} must agree on n")
    if not training.any():
        raise ValueError("no training superpixels: the safe zone selected none")
    if not 0.0 < threshold_quantile <= 1.0:
        raise ValueError(f"threshold_quantile must be in (0, 1], got {threshold_quantile}")
    x = features.astype(np.float64)
    scale = x.std(axis=0)
    scale[scale < 1e-9] = 1.0
    z = x / scale
    diff = z - z[training].mean(axis=0)
    ssd = np.einsum("ij,ij->i", diff, diff)
    threshold = float(np.quantile(ssd[training], threshold_quantile))
    return SsdClassification(
        ssd=ssd.astype(np.float32), threshold=threshold, is_floor=ssd <= threshold
    )
