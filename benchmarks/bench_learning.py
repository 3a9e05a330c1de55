"""Learning, not just running: two trials that must reach a success rate.

1. State-oracle SAC on ``fetch_reach``: success >= 0.9 within 10k env steps.
2. Pixel SAC with the ``pixel`` reward on ``point_reach``: success >= 0.8 within the
   printed budget, which must fit in 30 minutes on this CPU.

Run: ``.venv/bin/python benchmarks/bench_learning.py [fetch_reach_state|point_reach_pixel]``
(both by default). Prints every evaluation, then the figures. A task stops at its first
evaluation at or above the target (``--full``: run the whole budget). Wall time depends on
what else runs on the machine; the process CPU time printed next to it does not.
"""

from __future__ import annotations

import argparse
import time

import agent
from agent.config import SACConfig, TrialConfig

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
}


class Reached(Exception):
    """Raised from ``report`` to stop a trial once it reaches its target."""


def run(name: str, full: bool) -> bool:
    config, target = TASKS[name]
    start, cpu_start = time.perf_counter(), time.process_time()
    first: int | None = None

    def report(step: int, metrics: dict[str, float]) -> None:
        nonlocal first
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
        print(f"[{name}] outcome={result.outcome} AUC={result.auc:.3f}")
    except Reached:
        pass
    wall, cpu = (time.perf_counter() - start) / 60, (time.process_time() - cpu_start) / 60
    print(
        f"[{name}] success >= {target} first at env step {first} (budget {config.total_steps}); "
        f"wall {wall:.1f} min, cpu {cpu:.1f} min -> {'PASS' if first is not None else 'FAIL'}",
        flush=True,
    )
    return first is not None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tasks", nargs="*", choices=[*TASKS, []], default=list(TASKS))
    parser.add_argument("--full", action="store_true", help="run the whole budget")
    args = parser.parse_args()
    results = {name: run(name, args.full) for name in args.tasks}
    print("summary:", results)


if __name__ == "__main__":
    main()
