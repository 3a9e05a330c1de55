"""Learning, not just running: trials that must reach a success rate.

- ``fetch_reach_state``: state-oracle SAC on fetch_reach, success >= 0.9 within 10k steps.
- ``fetch_reach_true_reward``: SAC from 84x84 images with the env's true reward (the
  image control): success >= 0.8 within 20k env steps. It tells whether the agent can
  learn from these pixels at all, whatever the reward.
- ``fetch_reach_pixel``, ``fetch_reach_conv``, ``fetch_reach_linear``: the same trial
  with a learning-free latent reward; PIXEL must reach success >= 0.8 within 20k env
  steps (the thesis: PIXEL and CONV solve FetchReach from images); CONV and LINEAR are
  reported beside it. ``fetch_reach_conv_pytorch_init``: CONV with PyTorch's default
  initialisation (the CONV of this project before issue 20) instead of DrQ's.
- ``point_reach_pixel``: pixel SAC with the pixel reward on point_reach 32x32.
- ``fetch_reach_pixel_thesis``: the thesis' setting (84x84, 32 filters, batch 256, 2
  updates per step, 20k steps): hours per trial on a CPU, minutes on a GPU
  (``--device cuda``). Not run by default.

The fetch_reach image tasks use a CPU setting that keeps a trial well under an hour on
one core: 84x84 images, 16 filters, batch 32, 1 update per env step; every reward
scaled to about 1 (``reward_scale="auto"``; ``--reward-scale 1`` measures it unscaled).

Run: ``.venv/bin/python benchmarks/bench_learning.py [TASK ...] [--full] [--out DIR]``
(the default tasks: the two state/point checks and the fetch_reach true-reward and pixel
trials). Prints every evaluation, then the figures. A task stops at its first evaluation
at or above the target (``--full``: run the whole budget). ``--out DIR`` writes each
task's curve as ``DIR/<task>.csv`` and all curves in ``DIR/curves.png``. Wall time
depends on what else runs on the machine; the process CPU time printed next to it does not.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import time
from pathlib import Path

import agent
from agent.config import SACConfig, TrialConfig

#: the CPU setting of the fetch_reach image tasks (see the module docstring)
FETCH_CPU = TrialConfig(
    env="fetch_reach",
    image_size=84,
    method="pixel",
    sac=SACConfig(
        hidden_sizes=(256, 256),
        lr=1e-3,
        init_temperature=0.1,
        actor_update_every=2,
        critic_tau=0.01,
        batch_size=32,
        updates_per_step=1,
        buffer_capacity=100_000,
        num_filters=16,
    ),
    reward_scale="auto",
    total_steps=20_000,
    seed_steps=1_000,
    eval_every=1_000,
    eval_episodes=10,
    threads=1,
)

#: the thesis' appendix A.1 setting: FETCH_CPU with 32 filters, batch 256 and 2 updates per
#: env step (also ``bench_gpu_trial.py``'s)
FETCH_A1 = dataclasses.replace(
    FETCH_CPU,
    sac=dataclasses.replace(FETCH_CPU.sac, batch_size=256, updates_per_step=2, num_filters=32),
)

TASKS: dict[str, tuple[TrialConfig, float]] = {
    "fetch_reach_state": (
        TrialConfig(
            env="fetch_reach",
            method="state",
            sac=SACConfig(hidden_sizes=(256, 256), lr=1e-3, batch_size=256, updates_per_step=2),
            total_steps=10_000,
            seed_steps=1_000,
            eval_every=1_000,
            eval_episodes=20,
            threads=1,
        ),
        0.9,
    ),
    "point_reach_pixel": (
        TrialConfig(
            env="point_reach",
            image_size=32,
            method="pixel",
            sac=SACConfig(hidden_sizes=(256, 256), lr=1e-3, batch_size=64, updates_per_step=1),
            total_steps=10_000,
            seed_steps=500,
            eval_every=500,
            eval_episodes=10,
            threads=1,
        ),
        0.8,
    ),
    "fetch_reach_true_reward": (dataclasses.replace(FETCH_CPU, method="true_reward"), 0.8),
    "fetch_reach_pixel": (FETCH_CPU, 0.8),
    "fetch_reach_conv": (dataclasses.replace(FETCH_CPU, method="conv"), 0.8),
    "fetch_reach_conv_pytorch_init": (
        dataclasses.replace(FETCH_CPU, method="conv", encoder_params={"init": "pytorch"}),
        0.8,
    ),
    "fetch_reach_linear": (dataclasses.replace(FETCH_CPU, method="linear"), 0.8),
    "fetch_reach_pixel_thesis": (FETCH_A1, 0.8),
}
DEFAULT_TASKS = (
    "fetch_reach_state",
    "point_reach_pixel",
    "fetch_reach_true_reward",
    "fetch_reach_pixel",
)


class Reached(Exception):
    """Raised from ``report`` to stop a trial once it reaches its target."""


def run(name: str, config: TrialConfig, target: float, full: bool, out: Path | None) -> bool:
    start, cpu_start = time.perf_counter(), time.process_time()
    first: int | None = None
    rows: list[dict[str, float]] = []

    def report(step: int, metrics: dict[str, float]) -> None:
        nonlocal first
        rows.append({"step": step, **metrics})
        shown = "  ".join(f"{k}={v:.3f}" for k, v in metrics.items())
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        print(f"[{name}] step {step:>6}  {shown}  (wall {wall:.0f} s, cpu {cpu:.0f} s)", flush=True)
        if first is None and metrics["success_rate"] >= target:
            first = step
            if not full:
                raise Reached

    print(f"[{name}] {config}", flush=True)
    try:
        result = agent.train(config, report)
        print(f"[{name}] outcome={result.outcome} AUC={result.auc:.3f} "
              f"reward_scale={result.reward_scale:.4g}")  # fmt: skip
    except Reached:
        pass
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        with open(out / f"{name}.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    wall, cpu = (time.perf_counter() - start) / 60, (time.process_time() - cpu_start) / 60
    print(
        f"[{name}] success >= {target} first at env step {first} (budget {config.total_steps}); "
        f"wall {wall:.1f} min, cpu {cpu:.1f} min -> {'PASS' if first is not None else 'FAIL'}",
        flush=True,
    )
    return first is not None


def plot_curves(out: Path) -> None:
    """All ``out/*.csv`` curves in ``out/curves.png``: success rate and final distance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    for path in sorted(out.glob("*.csv")):
        with open(path) as f:
            rows = list(csv.DictReader(f))
        steps = [int(r["step"]) for r in rows]
        for ax, key in zip(axes, ("success_rate", "final_distance"), strict=True):
            if key in rows[0]:
                ax.plot(steps, [float(r[key]) for r in rows], marker=".", label=path.stem)
    for ax, label in zip(axes, ("success rate", "final distance (m)"), strict=True):
        ax.set_xlabel("env steps")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.savefig(out / "curves.png", dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tasks", nargs="*", choices=[*TASKS, []], default=list(DEFAULT_TASKS))
    parser.add_argument("--full", action="store_true", help="run the whole budget")
    parser.add_argument("--out", type=Path, default=None, help="write CSV curves and a PNG here")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument(
        "--reward-scale", default=None, help="override the tasks' reward_scale ('auto' or a number)"
    )
    args = parser.parse_args()
    results = {}
    for name in args.tasks:
        config, target = TASKS[name]
        changes: dict = {"seed": args.seed, "device": args.device}
        if args.reward_scale is not None:
            scale = args.reward_scale
            changes["reward_scale"] = scale if scale == "auto" else float(scale)
        results[name] = run(
            name, dataclasses.replace(config, **changes), target, args.full, args.out
        )
    if args.out is not None:
        plot_curves(args.out)
    print("summary:", results)


if __name__ == "__main__":
    main()
