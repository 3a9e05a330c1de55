"""Scalar summaries of a learning curve: pure numpy."""

from __future__ import annotations

import numpy as np


def normalized_auc(steps: object, values: object) -> float:
    """Area under ``values`` over ``steps`` (trapezoid rule) divided by the step range.

    A constant curve ``c`` gives ``c``; a success-rate curve gives a number in [0, 1].
    ``steps`` must be strictly increasing with at least two points, ``values`` aligned
    and finite.
    """
    x = np.asarray(steps, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"steps and values must be 1-D and aligned, got {x.shape} and {y.shape}")
    if x.size < 2:
        raise ValueError(f"need at least two evaluation points, got {x.size}")
    if not np.all(np.diff(x) > 0):
        raise ValueError(f"steps must be strictly increasing, got {x.tolist()}")
    if not np.all(np.isfinite(y)):
        raise ValueError(f"values must be finite, got {y.tolist()}")
    area = np.sum((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2.0)
    return float(area / (x[-1] - x[0]))


def evaluation_grid(total_steps: int, eval_every: int) -> tuple[int, ...]:
    """Env steps at which a trial evaluates: ``0, eval_every, ..., total_steps``.

    ``total_steps`` closes the grid even when it is not a multiple of ``eval_every``.
    """
    if total_steps < 1 or eval_every < 1:
        raise ValueError(
            f"total_steps and eval_every must be >= 1, got {total_steps}, {eval_every}"
        )
    grid = list(range(0, total_steps + 1, eval_every))
    if grid[-1] != total_steps:
        grid.append(total_steps)
    return tuple(grid)


def metric_key(info_name: str) -> str:
    """The reported name of an env metric: ``is_success`` -> ``success_rate``,
    ``<k>_success`` -> ``<k>_success_rate``, any other ``<k>`` -> ``final_<k>``."""
    if info_name == "is_success":
        return "success_rate"
    if info_name.endswith("_success"):
        return f"{info_name}_rate"
    return f"final_{info_name}"


def summarize_episodes(
    final_infos: list[dict[str, float]], metric_names: tuple[str, ...]
) -> dict[str, float]:
    """Mean of each metric over the episodes' final-step ``info``, under its reported name."""
    if not final_infos:
        raise ValueError("final_infos must hold at least one episode")
    return {
        metric_key(name): float(np.mean([info[name] for info in final_infos]))
        for name in metric_names
    }


def diverged_metrics(keys: tuple[str, ...]) -> dict[str, float]:
    """What a grid point after a divergence reports: success 0, every other metric NaN."""
    return {k: 0.0 if k == "success_rate" else float("nan") for k in keys}
