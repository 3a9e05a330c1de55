"""Time `sweeper aggregate` on a synthetic study of 2,000 trials x 50 evaluation points.

    .venv/bin/python benchmarks/bench_aggregate.py [--db PATH] [--trials 2000] [--points 50]

The study (4 methods x trials/4 configurations, sawyer_door metrics, written by
tests/synthetic_study.py through Optuna) is kept in ``--db`` and reused by later runs,
since writing it takes minutes. Prints the time to read it with ``load_study_frame`` and
with Optuna's ``get_trials``, and of the whole aggregation (CSV, figures, report,
dashboard figures and note), wall and CPU: on a busy machine the CPU time is the fairer
figure. Target: the whole aggregation under 10 s.
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

METHODS = ("pixel", "linear", "conv", "vae")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", type=Path, default=Path(tempfile.gettempdir()) / "bench_agg.db")
    parser.add_argument("--trials", type=int, default=2000)
    parser.add_argument("--points", type=int, default=50)
    args = parser.parse_args()

    import optuna
    from synthetic_study import write_synthetic_study

    from sweeper.results.cli_aggregate import aggregate, load_study_frame

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    name = f"bench_{args.trials}x{args.points}"
    url = f"sqlite:///{args.db}"
    if name not in {s.study_name for s in optuna.get_all_study_summaries(url)}:
        print(f"writing {name} to {args.db} (once; takes minutes)...", flush=True)
        start = time.perf_counter()
        write_synthetic_study(
            url,
            name,
            methods=METHODS,
            configs=args.trials // len(METHODS),
            steps=tuple(range(0, 1000 * args.points, 1000)),
        )
        print(f"  written in {time.perf_counter() - start:.0f} s")

    start = time.perf_counter()
    frame = load_study_frame(url, name)
    read = time.perf_counter() - start
    print(f"load_study_frame: {read:.2f} s ({frame['trial'].nunique()} trials, {len(frame)} rows)")

    start = time.perf_counter()
    optuna.load_study(study_name=name, storage=url).get_trials(deepcopy=False)
    print(f"optuna get_trials(deepcopy=False), for comparison: {time.perf_counter() - start:.2f} s")

    with tempfile.TemporaryDirectory() as out:
        start, cpu = time.perf_counter(), time.process_time()

        def progress(message: str) -> None:
            print(f"  {time.perf_counter() - start:5.1f} s  {message}", flush=True)

        aggregate(url, name, Path(out), progress=progress)
        whole, cpu = time.perf_counter() - start, time.process_time() - cpu
    print(
        f"whole aggregation (CSV, figures, report, dashboard): {whole:.2f} s wall, "
        f"{cpu:.2f} s CPU (target < 10 s); load average {os.getloadavg()[0]:.1f} "
        f"on {os.cpu_count()} CPUs"
    )


if __name__ == "__main__":
    main()
