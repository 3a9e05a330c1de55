"""Time one refresh of the dashboard figures a launch makes (``sweeper.results._live``).

    .venv/bin/python benchmarks/bench_live_figures.py [--methods 8] [--configs 3] \
        [--seeds 2] [--points 16] [--repeats 3]

Writes a synthetic study (tests/synthetic_study.py; the default is the size of
studies/fetch_reach_cpu.yaml: 8 methods x 3 configurations x 2 seeds = 48 trials, 16
evaluation points) into a temporary SQLite file and times ``refresh``: read the study,
compute the tables (every bootstrap), save the figures and the note, wall and CPU.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", type=int, default=8)
    parser.add_argument("--configs", type=int, default=3)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--points", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    import optuna
    from synthetic_study import write_synthetic_study

    from sweeper.results._live import refresh
    from sweeper.storage import StudyStore, open_storage

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    methods = tuple(f"method{i}" for i in range(args.methods))
    with tempfile.TemporaryDirectory() as folder:
        url = f"sqlite:///{Path(folder) / 'study.db'}"
        steps = tuple(1000 * i for i in range(args.points))
        write_synthetic_study(
            url,
            "live",
            methods=methods,
            configs=args.configs,
            seeds=tuple(range(args.seeds)),
            steps=steps,
            random_success=0.1,
        )
        store = StudyStore.find(open_storage(url), "live")
        assert store is not None
        walls, cpus = [], []
        for _ in range(args.repeats):
            wall, cpu = time.perf_counter(), time.process_time()
            refresh(store)
            walls.append(time.perf_counter() - wall)
            cpus.append(time.process_time() - cpu)
        trials = len(store.trials())
    print(
        f"refresh of {trials} trials x {args.points} points: wall {statistics.median(walls):.2f} s "
        f"(min {min(walls):.2f}), CPU {statistics.median(cpus):.2f} s, median of {args.repeats}"
    )


if __name__ == "__main__":
    main()
