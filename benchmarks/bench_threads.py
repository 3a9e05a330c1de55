"""Is a trial alone on the machine faster with more torch threads, and by how much?

A study's planned trials (``--keys``, default: one per gradient budget of
``studies/fetch_reach_budget.yaml``), each cut to ``--trial-steps`` env steps (the first
third random, ``bench_gpu_trial.measured_config``) and run alone at each of ``--threads``;
per row: env steps/s while learning, while seeding and while evaluating, the speed-up of
the learning phase over the first thread count, and the predicted wall time of the full
trial at those rates (``Phases.seconds_for``: setup, seed phase, learning, evaluations).

Why: on the AMD kinds a 1/2 trial of ``fetch_reach_budget`` takes longer than a session at
1 thread, two at once; one alone with both cores' threads might fit. Nothing else should run
on the machine while this does (each row is one trial: the machine's other cores idle).

Run: ``./run python benchmarks/bench_threads.py [--spec studies/fetch_reach_budget.yaml]
[--keys pixel_b128x2/0/0,pixel_b128/0/0] [--threads 1,2] [--trial-steps 300]``
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_gpu_trial import measured_config, positive_ints, run_together
from bench_update_speed import cpu_line

from sweeper.plan._entries import build_plan
from sweeper.plan._estimate import format_duration
from sweeper.spec._models import load_spec

SPEC = Path(__file__).resolve().parent.parent / "studies" / "fetch_reach_budget.yaml"
KEYS = "pixel_b128x2/0/0,pixel_b128/0/0,pixel_tau01/0/0"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spec", type=Path, default=SPEC)
    parser.add_argument("--keys", default=KEYS, help="comma-separated plan keys")
    parser.add_argument("--threads", type=positive_ints, default=[1, 2])
    parser.add_argument("--trial-steps", type=int, default=300, help="env steps per trial")
    args = parser.parse_args()
    if args.trial_steps < 3:
        parser.error("--trial-steps must be at least 3")
    try:
        entries = {e.key: e for e in build_plan(load_spec(args.spec)).entries}
    except ValueError as e:  # SpecError: a missing or bad spec, one line
        parser.error(str(e))
    keys = args.keys.split(",")
    unknown = [k for k in keys if k not in entries]
    if unknown:
        parser.error(f"not a key of {args.spec.name}: {', '.join(unknown)}")
    print(cpu_line())
    print(
        f"{args.spec.name}: each trial cut to {args.trial_steps} env steps, alone on the "
        "machine; the full trial predicted at the measured rates\n"
    )
    print("| trial | batch x updates | threads | learning steps/s | speed-up | seed steps/s | "
          "eval steps/s | full trial |")  # fmt: skip
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for key in keys:
        # no video: the cut trial's evaluation grid does not hold the full trial's video step
        full = dataclasses.replace(entries[key].trial_config, device="cpu", video_steps=())
        first = None
        for threads in args.threads:
            (phases,) = run_together(measured_config(full, args.trial_steps, "cpu", threads), 1)
            first = first or phases.learn_rate
            print(
                f"| {key} | {full.sac.batch_size} x {full.sac.updates_per_step} | {threads} | "
                f"{phases.learn_rate:.2f} | {phases.learn_rate / first:.2f}x | "
                f"{phases.seed_rate:.0f} | {phases.eval_rate:.0f} | "
                f"{format_duration(phases.seconds_for(full))} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
