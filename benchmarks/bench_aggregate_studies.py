"""Time `sweeper aggregate A.yaml B.yaml ...` (the combined report over several studies) on
synthetic studies of 2,000 trials x 50 evaluation points each.

    .venv/bin/python benchmarks/bench_aggregate_studies.py [--db PATH] [--studies 5]
        [--trials 2000] [--points 50]

Each study (4 methods, one the state-oracle control, x trials/4 configurations, a random
agent's success rate; written by tests/synthetic_study.py) has its own env name and is kept
in ``--db``, reused by later runs since writing one takes minutes. Prints the time of the
whole combined aggregation (reading every study, anchors, normalised scores with their
stratified intervals and profiles, per-study tables, figures, report), wall and CPU, and
the machine's load. Target: under 15 s for 5 studies.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

METHODS = ("pixel", "linear", "vae", "state")
ENVS = ("fetch_reach", "fetch_push", "sawyer_door", "point_reach")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--db", type=Path, default=Path(tempfile.gettempdir()) / "bench_agg_studies.db"
    )
    parser.add_argument("--studies", type=int, default=5)
    parser.add_argument("--trials", type=int, default=2000)
    parser.add_argument("--points", type=int, default=50)
    args = parser.parse_args()

    import optuna
    from synthetic_study import write_synthetic_study

    from sweeper.results._combined import aggregate_studies

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    url = f"sqlite:///{args.db}"
    names = [f"bench{i}_{args.trials}x{args.points}" for i in range(args.studies)]
    existing = (
        {s.study_name for s in optuna.get_all_study_summaries(url)} if args.db.exists() else set()
    )
    for index, name in enumerate(names):
        if name in existing:
            continue
        print(f"writing {name} to {args.db} (once; takes minutes)...", flush=True)
        start = time.perf_counter()
        write_synthetic_study(
            url,
            name,
            methods=METHODS,
            configs=args.trials // len(METHODS),
            steps=tuple(range(0, 1000 * args.points, 1000)),
            env=ENVS[index % len(ENVS)],
            random_success=0.02 * (index + 1),
            seed=index,
        )
        print(f"  written in {time.perf_counter() - start:.0f} s", flush=True)

    with tempfile.TemporaryDirectory() as out:
        start, cpu = time.perf_counter(), time.process_time()

        def progress(message: str) -> None:
            print(f"  {time.perf_counter() - start:5.1f} s  {message}", flush=True)

        aggregate_studies([(url, name) for name in names], Path(out), progress=progress)
        whole, cpu = time.perf_counter() - start, time.process_time() - cpu
    print(
        f"combined aggregation of {args.studies} studies x {args.trials} trials x "
        f"{args.points} points: {whole:.2f} s wall, {cpu:.2f} s CPU (target < 15 s); "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"
    )


if __name__ == "__main__":
    main()
