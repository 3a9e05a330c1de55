"""Comparison statistics for per-trial scores (AUCs): pure numpy functions.

- ``iqm``: interquartile mean, the mean of the middle 50 % (as rliable: drop
  ``floor(n / 4)`` values from each end of the sorted sample, i.e. ``scipy.stats.trim_mean``
  with ``proportiontocut=0.25``).
- ``bootstrap_ci`` / ``stratified_bootstrap_ci``: seeded percentile bootstrap confidence
  interval of a statistic; stratified means each method's trials are resampled only among
  themselves, with the method's own sample size.
- ``probability_of_improvement``: paired ``P(X > Y) + 0.5 P(X = Y)`` over the pairs of
  trials that share a SAC configuration and seed (the sweep's paired design).

The AUC itself is ``agent.metrics.normalized_auc`` (the trial computes it).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping

import numpy as np

#: a reduction called as ``statistic(samples, axis=-1)``
Statistic = Callable[..., np.ndarray | float]


def _as_sample(values: object, name: str = "values") -> np.ndarray:
    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D sequence, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} must be finite, got {x.tolist()}")
    return x


def iqm(values: object, axis: int = -1) -> np.ndarray | float:
    """Interquartile mean along ``axis``: sort, drop ``floor(n / 4)`` from each end, average.

    ``iqm([1, 2, 3, 4]) == 2.5`` (drops 1 and 4); ``iqm([1, 2, 3]) == 2`` (n < 4: plain mean).
    A 1-D input gives a float; with more dimensions the reduced array.
    """
    x = np.sort(np.asarray(values, dtype=np.float64), axis=axis)
    n = x.shape[axis]
    if n == 0:
        raise ValueError("iqm of an empty sample")
    cut = n // 4
    middle = np.take(x, np.arange(cut, n - cut), axis=axis)
    result = middle.mean(axis=axis)
    return float(result) if np.ndim(result) == 0 else result


def bootstrap_ci(
    values: object,
    statistic: Statistic = iqm,
    *,
    confidence: float = 0.95,
    resamples: int = 2000,
    rng: np.random.Generator,
) -> tuple[float, float]:
    """Percentile bootstrap CI of ``statistic``, called as ``statistic(samples, axis=-1)``
    (``iqm``, ``np.mean``, ``np.median``).

    Draws ``resamples`` samples of size n with replacement and returns the
    ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` quantiles of the statistic.
    """
    x = _as_sample(values)
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    stats = np.asarray(statistic(x[rng.integers(0, x.size, size=(resamples, x.size))], axis=-1))
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(stats, [alpha, 1.0 - alpha])
    return float(low), float(high)


def stratified_bootstrap_ci(
    samples: Mapping[str, object],
    statistic: Statistic = iqm,
    *,
    confidence: float = 0.95,
    resamples: int = 2000,
    seed: int = 0,
) -> dict[str, tuple[float, float]]:
    """Bootstrap CI of ``statistic`` for every stratum (method), each resampled on its own.

    Each stratum's generator is seeded from ``(seed, crc32(name))``, so a stratum's interval
    does not change when other strata are added or removed, and reruns are identical.
    """
    return {
        name: bootstrap_ci(
            values,
            statistic,
            confidence=confidence,
            resamples=resamples,
            rng=np.random.default_rng([seed, zlib.crc32(name.encode())]),
        )
        for name, values in samples.items()
    }


def probability_of_improvement(x: object, y: object) -> float:
    """Paired probability that X beats Y: mean of ``[x_i > y_i] + 0.5 [x_i == y_i]``.

    ``x[i]`` and ``y[i]`` must be the scores of two methods on the same pair (same SAC
    configuration and seed). 1.0: X better on every pair; 0.5: no difference.
    """
    a, b = _as_sample(x, "x"), _as_sample(y, "y")
    if a.shape != b.shape:
        raise ValueError(f"x and y must be paired (same length), got {a.size} and {b.size}")
    return float(np.mean((a > b) + 0.5 * (a == b)))
