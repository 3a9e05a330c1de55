"""Learning, not just running: two trials that must reach a success rate.

1. State-oracle SAC on ``fetch_reach``: success >= 0.9 within 10k env steps.
2. Pixel SAC with the ``pixel`` reward on ``point_reach``: success >= 0.8 within the
   printed budget, which must fit in 30 minutes on this CPU.

Run: ``.venv/bin/python benchmarks/bench_learning.py [fetch_reach_state|point_reach_pixel]``
(both by default). Prints every evaluation, then the figures.
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
            sac=SACConfig(hidden_sizes=(256, 256), lr=1e-3, batch_size=128, updates_per_step=1),
            total_steps=12_000,
            seed_steps=1_000,
            eval_every=1_000,
            eval_episodes=20,
            threads=1,
        ),
        0.8,
    ),
}


def run(name: str) -> bool:
    config, target = TASKS[name]
    start = time.perf_counter()

    def report(step: int, metrics: dict[str, float]) -> None:
        shown = "  ".join(f"{k}={v:.3f}" for k, v in metrics.items())
        print(
            f"[{name}] step {step:>6}  {shown}  ({time.perf_counter() - start:.0f} s)", flush=True
        )

    print(f"[{name}] {config}", flush=True)
    result = agent.train(config, report)
    success = result.metrics["success_rate"]
    first = next((s for s, v in zip(result.steps, success, strict=True) if v >= target), None)
    ok = first is not None
    print(
        f"[{name}] outcome={result.outcome} best success={max(success):.2f} "
        f"(target {target}) first reached at step {first} of {config.total_steps}; "
        f"AUC={result.auc:.3f}; wall time {result.seconds / 60:.1f} min "
        f"-> {'PASS' if ok else 'FAIL'}",
        flush=True,
    )
    return ok


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tasks", nargs="*", choices=[*TASKS, []], default=list(TASKS))
    args = parser.parse_args()
    results = {name: run(name) for name in args.tasks}
    print("summary:", results)


if __name__ == "__main__":
    main()
