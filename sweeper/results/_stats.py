"""Comparison statistics for per-trial scores (AUCs) and their intervals: pure numpy.

Statistics are small functions over arrays, as in rliable, each reducing the axis of the
units (trials, or pairs of trials) and vectorised over the others so one call covers every
bootstrap replicate:

- ``iqm``: interquartile mean, the mean of the middle 50 % (as rliable: drop
  ``floor(n / 4)`` values from each end of the sorted sample, i.e. ``scipy.stats.trim_mean``
  with ``proportiontocut=0.25``); robust to the few outlier trials a sweep always has,
  more precise than the median.
- ``mean``, ``median``, ``optimality_gap`` (how far below ``threshold`` the scores fall).
- ``probability_of_improvement``: paired ``P(X > Y) + 0.5 P(X = Y)`` over the pairs of
  trials that share a SAC configuration and seed (the sweep's paired design).
- ``score_profile``: the fraction of scores above each threshold tau (a performance
  profile, Agarwal et al. 2021).
- ``normalize``: scores of different tasks on one scale between two anchors (as Atari's
  human-normalised scores), so studies of several envs can be pooled.

The resampling is separate: ``stratified_bootstrap`` is the one routine behind every
interval. A ``Group`` holds aligned arrays whose first axis is the unit resampled as a whole
(a trial's AUC, a trial's whole curve, or a pair of paired AUCs), and optionally the
stratum of each unit (the study, when scores of several studies are pooled): a unit is
replaced only by a unit of its own stratum, so each stratum keeps its size in every
replicate. Intervals are percentile intervals, seeded per group name.

The AUC itself is ``agent.metrics.normalized_auc`` (the trial computes it).
"""

from __future__ import annotations

import functools
import math
import zlib
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np

#: a reduction called as ``statistic(*arrays, axis=...)``; the result may have trailing axes
Statistic = Callable[..., np.ndarray | float]
#: elements per bootstrap chunk (8 bytes each): bounds the memory of big resamples
CHUNK_ELEMENTS = 1 << 22


def _as_sample(values: object, name: str = "values") -> np.ndarray:
    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D sequence, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} must be finite, got {x.tolist()}")
    return x


def _scalar(result: np.ndarray) -> np.ndarray | float:
    return float(result) if np.ndim(result) == 0 else result


# ---- statistics ------------------------------------------------------------------------


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
    return _scalar(middle.mean(axis=axis))


def mean(values: object, axis: int = -1) -> np.ndarray | float:
    """Arithmetic mean along ``axis``: sensitive to outliers, reported for completeness."""
    return _scalar(np.mean(np.asarray(values, dtype=np.float64), axis=axis))


def median(values: object, axis: int = -1) -> np.ndarray | float:
    """Median along ``axis``: robust, but uses only the one or two middle scores."""
    return _scalar(np.median(np.asarray(values, dtype=np.float64), axis=axis))


def optimality_gap(values: object, axis: int = -1, threshold: float = 1.0) -> np.ndarray | float:
    """Mean shortfall below ``threshold``: ``mean(max(threshold - x, 0))``; lower is better.

    Scores above the threshold count as reaching it, so a method is not rewarded for
    overshooting on a few trials (rliable's ``aggregate_optimality_gap``).
    """
    x = np.asarray(values, dtype=np.float64)
    return _scalar(np.maximum(threshold - x, 0.0).mean(axis=axis))


def probability_of_improvement(x: object, y: object, axis: int = -1) -> np.ndarray | float:
    """Paired probability that X beats Y: mean of ``[x_i > y_i] + 0.5 [x_i == y_i]``.

    ``x[i]`` and ``y[i]`` must be the scores of two methods on the same pair (same SAC
    configuration and seed). 1.0: X better on every pair; 0.5: no difference.
    """
    a, b = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if a.ndim == 1 or b.ndim == 1:
        a, b = _as_sample(a, "x"), _as_sample(b, "y")
    if a.shape != b.shape:
        raise ValueError(f"x and y must be paired (same length), got {a.size} and {b.size}")
    return _scalar(np.mean((a > b) + 0.5 * (a == b), axis=axis))


def score_profile(values: object, taus: object, axis: int = -1) -> np.ndarray:
    """Fraction of ``values`` strictly above each ``tau`` (a performance profile).

    The reduced axis is replaced by a last axis over ``taus`` (sorted ascending):
    ``score_profile([0.2, 0.6], [0, 0.5, 1]) == [1, 0.5, 0]``. Counted by binning each
    value among the taus, so a (replicates x trials) array costs one pass, not one per tau.
    """
    x = np.moveaxis(np.asarray(values, dtype=np.float64), axis, -1)
    t = np.asarray(taus, dtype=np.float64)
    if t.ndim != 1 or np.any(np.diff(t) <= 0):
        raise ValueError("taus must be a strictly increasing 1-D sequence")
    below = np.searchsorted(t, x, side="left")  # how many taus lie strictly below each value
    rows = below.reshape(-1, x.shape[-1]) + (t.size + 1) * np.arange(x[..., 0].size)[:, None]
    counts = np.bincount(rows.ravel(), minlength=x[..., 0].size * (t.size + 1))
    counts = counts.reshape(*x.shape[:-1], t.size + 1)
    above = np.cumsum(counts[..., ::-1], axis=-1)[..., ::-1][..., 1:]  # values with > j taus below
    return above / x.shape[-1]


def normalize(values: object, zero: float, one: float) -> np.ndarray:
    """``(x - zero) / (one - zero)``: scores of different tasks on one scale, 0 at the
    ``zero`` anchor (a random agent), 1 at the ``one`` anchor (a reference method).

    Affine, so the IQM, mean and median of normalised scores are the normalised statistics
    and the ranking within a task is kept. ``one`` must lie above ``zero``: otherwise the
    task gives no scale (its reference does no better than chance).
    """
    if not (math.isfinite(zero) and math.isfinite(one)) or one <= zero:
        raise ValueError(f"normalise needs finite anchors with one > zero, got {zero}, {one}")
    return (np.asarray(values, dtype=np.float64) - zero) / (one - zero)


def several(*statistics: Statistic) -> Statistic:
    """One statistic stacking several along a last axis, so they share one resample
    (rliable's ``aggregate_func`` returning a vector)."""

    def stacked(*arrays: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.stack([np.asarray(f(*arrays, axis=axis)) for f in statistics], axis=-1)

    return stacked


#: the per-method summaries of a score sample, in report order (lower is better for the gap)
SUMMARIES: dict[str, Statistic] = {
    "iqm": iqm,
    "mean": mean,
    "median": median,
    "optimality_gap": optimality_gap,
}


def profile_statistic(taus: Sequence[float] | np.ndarray) -> Statistic:
    """``score_profile`` at fixed ``taus``, as a one-sample statistic."""
    return functools.partial(score_profile, taus=np.asarray(taus, dtype=np.float64))


# ---- resampling ----------------------------------------------------------------------


class Group(NamedTuple):
    """What one interval is computed from: ``arrays`` aligned along axis 0, whose rows
    (units) are resampled together, and optionally each unit's stratum label."""

    arrays: tuple[np.ndarray, ...]
    strata: np.ndarray | None = None


class Interval(NamedTuple):
    """A statistic on the data (``point``) and its percentile bootstrap interval."""

    point: np.ndarray | float
    low: np.ndarray | float
    high: np.ndarray | float


def as_group(data: Group | object) -> Group:
    """A ``Group`` from a group or from one sequence of scores; checks it."""
    group = data if isinstance(data, Group) else Group((np.asarray(data, dtype=np.float64),))
    arrays = tuple(np.asarray(a, dtype=np.float64) for a in group.arrays)
    n = arrays[0].shape[0] if arrays and arrays[0].ndim else 0
    if n == 0:
        raise ValueError("a bootstrap group needs a non-empty sample")
    for array in arrays:
        if array.ndim == 0 or array.shape[0] != n:
            raise ValueError(f"the arrays of a group must be aligned along axis 0 ({n} units)")
        if not np.all(np.isfinite(array)):
            raise ValueError("bootstrap samples must be finite")
    strata = None if group.strata is None else np.asarray(group.strata)
    if strata is not None and strata.shape != (n,):
        raise ValueError(f"strata must label each of the {n} units, got shape {strata.shape}")
    return Group(arrays, strata)


def bootstrap_indices(strata: np.ndarray, reps: int, rng: np.random.Generator) -> np.ndarray:
    """``(reps, n)`` unit indices: each position drawn uniformly, with replacement, from the
    units of its own stratum (one stratum: ``rng.integers(0, n, (reps, n))``, as scipy)."""
    indices = np.empty((reps, strata.size), dtype=np.intp)
    for label in np.unique(strata):
        members = np.flatnonzero(strata == label)
        indices[:, members] = members[rng.integers(0, members.size, (reps, members.size))]
    return indices


def bootstrap_replicates(
    statistic: Statistic, group: Group, *, reps: int, rng: np.random.Generator
) -> np.ndarray:
    """``statistic`` on ``reps`` resamples of ``group``: shape ``(reps, *statistic's)``.

    Drawn in chunks of at most ``CHUNK_ELEMENTS`` resampled values, so 2,000 replicates of
    500 curves x 50 points do not need 4 GB at once.
    """
    if reps < 1:
        raise ValueError(f"resamples must be >= 1, got {reps}")
    n = group.arrays[0].shape[0]
    strata = np.zeros(n, dtype=np.int64) if group.strata is None else group.strata
    chunk = max(1, min(reps, CHUNK_ELEMENTS // sum(a.size for a in group.arrays)))
    parts = []
    for start in range(0, reps, chunk):
        indices = bootstrap_indices(strata, min(chunk, reps - start), rng)
        parts.append(np.asarray(statistic(*(a[indices] for a in group.arrays), axis=1)))
    return np.concatenate(parts)


def percentile_interval(
    replicates: np.ndarray, confidence: float = 0.95
) -> tuple[np.ndarray, np.ndarray]:
    """The ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` quantiles over axis 0."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(replicates, [alpha, 1.0 - alpha], axis=0)
    return low, high


def stratified_bootstrap(
    statistic: Statistic,
    groups: Mapping[str, Group | object],
    *,
    reps: int = 2000,
    seed: int = 0,
    confidence: float = 0.95,
) -> dict[str, Interval]:
    """``statistic`` with its percentile bootstrap interval for every group (method, or
    method pair), each resampled on its own and within its strata.

    Each group's generator is seeded from ``(seed, crc32(name))``, so a group's interval
    does not change when other groups are added or removed, and reruns are identical.
    """
    intervals = {}
    for name, data in groups.items():
        group = as_group(data)
        rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
        replicates = bootstrap_replicates(statistic, group, reps=reps, rng=rng)
        low, high = percentile_interval(replicates, confidence)
        point = statistic(*group.arrays, axis=0)
        intervals[name] = Interval(point, _scalar(low), _scalar(high))
    return intervals


def bootstrap_ci(
    values: object,
    statistic: Statistic = iqm,
    *,
    confidence: float = 0.95,
    resamples: int = 2000,
    rng: np.random.Generator,
) -> tuple[float, float]:
    """Percentile bootstrap CI of ``statistic`` (``iqm``, ``np.mean``, ``np.median``) over
    one sample, drawn from ``rng``: ``resamples`` samples of size n with replacement."""
    x = _as_sample(values)
    replicates = bootstrap_replicates(statistic, Group((x,)), reps=resamples, rng=rng)
    low, high = percentile_interval(replicates, confidence)
    return float(low), float(high)


def stratified_bootstrap_ci(
    samples: Mapping[str, object],
    statistic: Statistic = iqm,
    *,
    confidence: float = 0.95,
    resamples: int = 2000,
    seed: int = 0,
) -> dict[str, tuple[float, float]]:
    """``stratified_bootstrap``'s intervals without the point estimates."""
    intervals = stratified_bootstrap(
        statistic,
        {name: _as_sample(values) for name, values in samples.items()},
        reps=resamples,
        seed=seed,
        confidence=confidence,
    )
    return {name: (float(i.low), float(i.high)) for name, i in intervals.items()}
