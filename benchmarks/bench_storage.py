"""Driver write cost per report, on SQLite (WAL) alone, SQLite with a reader, and PostgreSQL.

    .venv/bin/python benchmarks/bench_storage.py [--reports 200]

A report is what the driver writes each time a trial evaluates: one intermediate value and
the trial's whole ``curve`` user attr (here 5 metrics, growing to ``--reports`` points). The
reader is a separate process opening the database as optuna-dashboard does and reading every
trial in a loop. Prints milliseconds per report (median and max) and the reader's errors.
PostgreSQL runs on 127.0.0.1:5432 (database ``test``) in a throwaway schema.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import optuna
import psycopg

from sweeper.storage import StudyStore, open_storage

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_storage import READER  # the dashboard-like reader of the tests

optuna.logging.set_verbosity(optuna.logging.WARNING)


def run(url: str, reports: int, with_reader: bool, workdir: Path) -> str:
    name = f"bench-{uuid.uuid4().hex[:6]}"
    store = StudyStore.open_or_create(open_storage(url), name, {"plan_hash": "b"})
    reader = None
    stop = workdir / f"stop-{uuid.uuid4().hex[:6]}"
    if with_reader:
        reader = subprocess.Popen(
            [sys.executable, "-c", READER, url, str(stop)], stdout=subprocess.PIPE, text=True
        )
        time.sleep(2)  # let it start reading
    trial = store.add_waiting({"lr": 1e-3}, {"lr": (1e-3,)}, {"key": "m/0/0"})
    store.start(trial._trial_id)
    curve: dict[str, list[float]] = {k: [] for k in ("step", "a", "b", "c", "d", "e")}
    times = []
    for step in range(reports):
        for values in curve.values():
            values.append(float(step))
        start = time.perf_counter()
        store.report(trial._trial_id, {step: step / reports})
        store.set_attrs(trial._trial_id, {"curve": curve})
        times.append(time.perf_counter() - start)
    store.complete(trial._trial_id, 0.5, {"outcome": "completed"})
    line = f"median {1000 * statistics.median(times):6.1f} ms, max {1000 * max(times):7.1f} ms"
    if reader is not None:
        stop.touch()
        result = json.loads(reader.communicate(timeout=120)[0])
        line += f"; reader: {result['reads']} full reads, {result['n_errors']} errors"
    return line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reports", type=int, default=200)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        url = f"sqlite:///{workdir / 'bench.db'}"
        print(f"sqlite (WAL), alone:       {run(url, args.reports, False, workdir)}")
        print(f"sqlite (WAL), with reader: {run(url, args.reports, True, workdir)}")
        schema = f"bench_{uuid.uuid4().hex[:8]}"
        admin = "host=127.0.0.1 port=5432 dbname=test user=postgres"
        with psycopg.connect(admin, autocommit=True) as connection:
            connection.execute(f"CREATE SCHEMA {schema}")
        try:
            pg = f"postgresql://postgres@127.0.0.1:5432/test?options=-csearch_path%3D{schema}"
            print(f"postgresql, alone:         {run(pg, args.reports, False, workdir)}")
            print(f"postgresql, with reader:   {run(pg, args.reports, True, workdir)}")
        finally:
            with psycopg.connect(admin, autocommit=True) as connection:
                connection.execute(f"DROP SCHEMA {schema} CASCADE")


if __name__ == "__main__":
    main()
