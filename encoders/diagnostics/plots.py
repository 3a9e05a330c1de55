"""PNG figures of the diagnostics tables (matplotlib, Agg backend, no display needed)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grid(n: int, width: float = 4.0, height: float = 3.5, cols: int = 3):
    plt = _pyplot()
    cols = min(cols, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, height * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, axes.flat


def _save(fig, path: Path, title: str) -> Path:
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    _pyplot().close(fig)
    return path


def plot_exploration(table: pd.DataFrame, path: Path, title: str) -> Path:
    """Bar chart of the random agent's success rates."""
    fig, (ax,) = _grid(1, 6, 3.5)
    ax.bar(table["metric"], table["value"], color="tab:blue", label="random agent")
    ax.set_xlabel("flag set at any step of an episode (success_rate: any flag)")
    ax.set_ylabel("share of episodes")
    ax.set_ylim(0, 1)
    ax.legend()
    return _save(fig, path, title)


def plot_gradient(table: pd.DataFrame, path: Path, title: str) -> Path:
    """Box plot of the per-state cosine distances, one box per encoder; samples without a
    true gradient (NaN: goal at the start) are left out, as the summary's mean leaves them."""
    names = list(dict.fromkeys(table["encoder"]))
    fig, (ax,) = _grid(1, max(6.0, 1.2 * len(names)), 3.5)
    data = [table.loc[table["encoder"] == n, "value"].dropna().to_numpy() for n in names]
    ax.boxplot(data, tick_labels=names, showmeans=True)
    ax.axhline(1.0, color="gray", linestyle="--", label="orthogonal (no agreement)")
    ax.set_xlabel("encoder")
    ax.set_ylabel("cosine distance to true gradient")
    ax.set_ylim(0, 2)
    ax.legend(loc="upper right")
    return _save(fig, path, title)


def plot_correlation(pairs: pd.DataFrame, summary: pd.DataFrame, path: Path, title: str) -> Path:
    """Scatter of latent vs true reward, one panel per encoder, with Pearson and Spearman."""
    names = list(dict.fromkeys(pairs["encoder"]))
    fig, axes = _grid(len(names))
    for ax, name in zip(axes, names, strict=False):
        p = pairs[pairs["encoder"] == name]
        s = summary[summary["encoder"] == name].set_index("metric")["value"]
        ax.scatter(p["true_reward"], p["latent_reward"], s=6, alpha=0.5, label="(state, goal)")
        ax.set_title(f"{name}: pearson {s['pearson']:.2f}, spearman {s['spearman']:.2f}")
        ax.set_xlabel("true reward -||s - g||")
        ax.set_ylabel("latent reward -||phi(o) - phi(o_g)||")
        ax.legend(loc="best")
    return _save(fig, path, title)


def plot_precision(goals: pd.DataFrame, success_radius: float, path: Path, title: str) -> Path:
    """Per encoder, each goal's peak distance (left, with the success radius) and success
    AUC (right, with chance)."""
    names = list(dict.fromkeys(goals["encoder"]))
    fig, (left, right) = _grid(2, max(5.0, 1.1 * len(names)), 3.8, cols=2)
    for ax, metric, line, label in (
        (left, "peak_distance", success_radius, "success radius"),
        (right, "success_auc", 0.5, "chance"),
    ):
        data = [goals.loc[(goals["encoder"] == n) & (goals["metric"] == metric), "value"]
                .dropna().to_numpy() for n in names]  # fmt: skip
        ax.boxplot(data, tick_labels=names, showmeans=True)
        ax.axhline(line, color="gray", linestyle="--", label=label)
        ax.set_xlabel("encoder (true_reward: the true reward)")
        ax.legend(loc="best")
    left.set_ylabel("distance of the reward's peak to the goal")
    right.set_ylabel("P(success state > near miss)")
    right.set_ylim(0, 1.05)
    return _save(fig, path, title)


def plot_topology(embedding: pd.DataFrame, path: Path, title: str, labels: tuple[str, str]) -> Path:
    """Isomap embeddings of the grid latents, coloured by each grid coordinate."""
    plt = _pyplot()
    names = list(dict.fromkeys(embedding["encoder"]))
    fig, axes = plt.subplots(len(names), 2, figsize=(9, 3.8 * len(names)), squeeze=False)
    for row, name in zip(axes, names, strict=True):
        e = embedding[embedding["encoder"] == name]
        for ax, column, label in zip(row, ("state_a", "state_b"), labels, strict=True):
            points = ax.scatter(e["iso_x"], e["iso_y"], c=e[column], cmap="viridis", s=14)
            fig.colorbar(points, ax=ax, label=label)
            ax.set_title(f"{name}: coloured by {label}")
            ax.set_xlabel("isomap 1")
            ax.set_ylabel("isomap 2")
    return _save(fig, path, title)


def plot_variance(table: pd.DataFrame, path: Path, title: str) -> Path:
    """Per-dimension latent variance, arm moving vs object moving, one panel per encoder."""
    per_dim = table[table["dim"] >= 0]
    names = list(dict.fromkeys(per_dim["encoder"]))
    fig, axes = _grid(len(names))
    for ax, name in zip(axes, names, strict=False):
        t = per_dim[per_dim["encoder"] == name]
        arm = t.loc[t["metric"] == "arm_variance", "value"].to_numpy()
        obj = t.loc[t["metric"] == "object_variance", "value"].to_numpy()
        # a floor lets the log axes show dimensions with zero variance
        floor = max(float(np.concatenate([arm, obj]).max()) * 1e-9, 1e-30)
        ax.scatter(obj + floor, arm + floor, s=8, alpha=0.6, label="latent dimension")
        both = np.concatenate([arm, obj]) + floor
        lim = [float(both.min()), float(both.max())]
        ax.plot(lim, lim, color="gray", linestyle="--", label="equal variance")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("variance, only the object moves")
        ax.set_ylabel("variance, only the arm moves")
        ax.legend(loc="upper left")
    return _save(fig, path, title)


def plot_descent(episodes: pd.DataFrame, path: Path, title: str) -> Path:
    """Greedy descent: success rate per controller (left) and each episode's final
    distance to the goal (right, the median marked)."""
    plt = _pyplot()
    names = list(dict.fromkeys(episodes["encoder"]))
    fig, (left, right) = plt.subplots(1, 2, figsize=(max(8.0, 1.6 * len(names) + 4), 3.8))
    rates = [episodes.loc[episodes["encoder"] == n, "success"].mean() for n in names]
    colors = ["0.6" if n in ("random", "true_reward") else "C0" for n in names]
    left.bar(names, rates, color=colors)
    left.set_ylim(0, 1)
    left.set_ylabel("success rate")
    for i, name in enumerate(names):
        values = episodes.loc[episodes["encoder"] == name, "final_distance"].to_numpy()
        jitter = np.linspace(-0.15, 0.15, len(values)) if len(values) > 1 else np.zeros(1)
        right.scatter(i + jitter, values, s=10, alpha=0.6, color=colors[i])
        right.hlines(np.median(values), i - 0.3, i + 0.3, color="k")
    right.set_xticks(range(len(names)), names)
    right.set_ylabel("final distance to the goal")
    for ax in (left, right):
        ax.tick_params(axis="x", rotation=30)
    return _save(fig, path, title)
