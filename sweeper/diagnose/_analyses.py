"""The analyses of ``sweeper diagnose``: each runs one of ``encoders.diagnostics`` on an
env, writes its CSV and figure, and returns its summary rows. Imported only when an env is
diagnosed (pandas, scipy, scikit-learn, matplotlib)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from encoders import diagnostics as dx
from encoders.diagnostics import plots
from sweeper.diagnose._settings import ARM_OBJECT_ENVS, Settings, grid_dims
from sweeper.spec import plural


@dataclass(frozen=True)
class Target:
    """One env under diagnosis: its name, the env, the encoders and the output folder."""

    name: str
    env: Any
    encoders: dict[str, Any]
    out: Path

    def write(self, table: pd.DataFrame, stem: str) -> pd.DataFrame:
        """``table`` with an ``env`` column first, written to ``<out>/<stem>.csv``."""
        table = table.copy()
        table.insert(0, "env", self.name)
        table.to_csv(self.out / f"{stem}.csv", index=False)
        return table


def _exploration(settings: Settings, target: Target) -> pd.DataFrame:
    table = dx.random_exploration(
        target.env, settings.episodes, seed=settings.seed, progress=not settings.quiet
    )
    table = target.write(table, "exploration")
    plots.plot_exploration(table, target.out / "exploration.png", f"{target.name}: random agent")
    return table.assign(analysis="exploration")


def _gradient(settings: Settings, target: Target) -> pd.DataFrame:
    table = dx.gradient_agreement(
        target.env,
        target.encoders,
        settings.gradient_states,
        settings.directions,
        settings.alpha,
        seed=settings.seed,
        start=settings.start,
        min_goal_distance=settings.min_goal_distance,
        progress=not settings.quiet,
    )
    target.write(table.assign(start=settings.start), "gradient")
    plots.plot_gradient(
        table,
        target.out / "gradient.png",
        f"{target.name}: latent vs true reward gradient (Algorithm 1, start {settings.start})",
    )
    summary = dx.gradient_summary(table)
    return summary.assign(env=target.name, analysis="gradient", start=settings.start)


def _correlation(settings: Settings, target: Target) -> pd.DataFrame:
    summary, pairs = dx.reward_correlation(
        target.env,
        target.encoders,
        settings.pairs,
        seed=settings.seed,
        start=settings.start,
        progress=not settings.quiet,
    )
    summary = target.write(summary.assign(start=settings.start), "correlation")
    pairs = target.write(pairs.assign(start=settings.start), "correlation_pairs")
    plots.plot_correlation(
        pairs,
        summary,
        target.out / "correlation.png",
        f"{target.name}: latent vs true reward, start {settings.start}",
    )
    return summary.assign(analysis="correlation")


def _precision(settings: Settings, target: Target) -> pd.DataFrame:
    summary, goals = dx.goal_precision(
        target.env,
        target.encoders,
        settings.precision_goals,
        settings.precision_states,
        settings.precision_radius,
        settings.success_radius,
        seed=settings.seed,
        progress=not settings.quiet,
    )
    summary = target.write(summary, "precision")
    goals = target.write(goals, "precision_goals")
    plots.plot_precision(
        goals,
        settings.success_radius,
        target.out / "precision.png",
        f"{target.name}: where the latent reward peaks within {settings.precision_radius} "
        "of the goal",
    )
    return summary.assign(analysis="precision")


def _topology(settings: Settings, target: Target) -> pd.DataFrame:
    env = target.env
    dims = grid_dims(settings.grid_dims, tuple(env.state_names))
    summary, embedding = dx.grid_topology(
        env, target.encoders, settings.grid_size, dims, seed=settings.seed,
        progress=not settings.quiet,
    )  # fmt: skip
    summary = target.write(summary, "topology")
    embedding = target.write(embedding, "topology_embedding")
    a, b = dims or dx.default_grid_dims(env)
    plots.plot_topology(
        embedding,
        target.out / "topology.png",
        f"{target.name}: isomap of a {settings.grid_size}x{settings.grid_size} state grid",
        (env.state_names[a], env.state_names[b]),
    )
    return summary.assign(analysis="topology")


def _variance(settings: Settings, target: Target) -> pd.DataFrame | None:
    if target.name not in ARM_OBJECT_ENVS:
        settings.log(
            f"{target.name}: the variance analysis is for {', '.join(ARM_OBJECT_ENVS)}; skipped"
        )
        return None
    table = dx.arm_object_variance(
        target.env,
        target.encoders,
        settings.variance_states,
        seed=settings.seed,
        progress=not settings.quiet,
    )
    table = target.write(table, "variance")
    plots.plot_variance(
        table,
        target.out / "variance.png",
        f"{target.name}: latent variance, arm moving vs object moving",
    )
    return table[table["dim"] < 0].drop(columns="dim").assign(analysis="variance")


def _descent(settings: Settings, target: Target) -> pd.DataFrame:
    summary, episodes = dx.greedy_descent(
        target.env,
        target.encoders,
        settings.descent_episodes,
        settings.descent_horizon,
        settings.descent_candidates,
        settings.descent_step,
        seed=settings.seed,
        progress=not settings.quiet,
    )
    summary = target.write(summary, "descent")
    episodes = target.write(episodes, "descent_episodes")
    plots.plot_descent(
        episodes,
        target.out / "descent.png",
        f"{target.name}: greedy descent on each reward "
        f"({plural(settings.descent_candidates, 'candidate')} a step, "
        f"{plural(settings.descent_horizon, 'step')})",
    )
    return summary.assign(analysis="descent")


#: analysis name -> the function that runs it, writes its CSV and PNG and returns its summary
#: (in the order they run)
RUNNERS: dict[str, Callable[[Settings, Target], pd.DataFrame | None]] = {
    "exploration": _exploration,
    "gradient": _gradient,
    "correlation": _correlation,
    "precision": _precision,
    "topology": _topology,
    "variance": _variance,
    "descent": _descent,
}
