"""Concurrency benchmark: the same small point_reach study with 1 and 2 trials at once.

    .venv/bin/python benchmarks/bench_concurrency.py [--trials 4] [--env-steps 5000]
        [--repeat 1] [--ray both|head|local] [--address ADDR]

Each run is a real ``sweeper launch`` (a subprocess: Python and torch imports, Ray (its own
or a running one), the study database, the worker actors, the driver loop) on a fresh SQLite
study in a temporary directory. For a run with ``c`` trials at once it prints:

- ``wall``: seconds from starting ``sweeper launch`` to its exit (W);
- ``in trials``: the sum over trials of the time each trial measured inside
  ``agent.train`` (``TrialResult.seconds``, stored as the ``seconds`` user attr) (S);
- ``outside``: the issue's orchestration overhead, time outside trials / total: the share of
  W during which no trial was in flight (from its dispatch, Optuna's ``datetime_start``, to
  its result being written, ``datetime_complete``): start-up (imports, Ray, database),
  shut-down, and any moment between trials;
- ``idle slots = 1 - S / (c * W)``: stricter: the share of the ``c`` trial slots' time not
  spent inside a trial. It also counts a slot that waits while the other one finishes the
  study's last trial (trials of one budget still differ in length by some seconds), so it
  depends on how many trials each slot gets. It does not count two trials slowing each
  other down by sharing the CPU (that shows in S);
- ``startup``: seconds from start to the first trial's start (Optuna's ``datetime_start``)
  and ``tail``: from the last trial's end (``datetime_complete``) to the exit: the fixed
  part of the overhead, which a longer study amortises;
- ``steady = 1 - S / (c * (W - startup - tail))``: idle slots while trials run
  (dispatching, streaming and writing results, a slot waiting for the last trial);
- ``gap``: per trial, its span in the study (``datetime_complete - datetime_start``) minus
  its in-trial time, shown as the mean over the first ``c`` trials (each on a fresh worker
  process that still imports torch and the agent: a one-off warm-up per worker) and the
  mean over the later ones (the per-trial cost of dispatching and recording);
- ``speed-up`` (for c = 2): W(c=1) / W(c=2).

The target is an overhead under 5%. Each configuration runs twice over (``--ray both``,
the default): on a running one-node Ray cluster (a ``ray start --head`` that the benchmark
starts first, as docs/cluster.md starts one; each launch joins it with ``--address``, as on
a cluster), and with each launch starting and stopping its own local Ray (``sweeper
launch`` without ``--address``), which adds Ray's own start and stop (~5-7 s) to every
study. The fixed start-up and tail (that, and each worker importing torch; seconds more on a
machine whose page cache has been emptied) do not grow with the study, so the benchmark
also prints the study wall time from which the idle-slot share stays under 5%.
``--address`` runs on a cluster that is already up instead.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
#: for the head the benchmark starts, and for the drivers joining it (docs/cluster.md)
HEAD_ENV = {"RAY_AUTH_MODE": "token", "RAY_USAGE_STATS_ENABLED": "0"}


def run_study(
    workdir: Path, trials: int, env_steps: int, concurrency: int, address: str | None
) -> dict[str, float]:
    """Launch the study with ``concurrency`` trials at once; return its figures."""
    import optuna

    from sweeper.spec._models import load_yaml

    study = f"bench_concurrency_c{concurrency}"
    spec = load_yaml((REPO / "studies" / "ci.yaml").read_text())  # tiny point_reach trials
    spec.update(study=study, methods={"pixel": {}}, trials_per_method=trials)
    eval_every = max(50, env_steps // 5 // 50 * 50)
    spec["budget"].update(env_steps=env_steps, eval_every=eval_every)
    spec["execution"].update(max_concurrent=concurrency, checkpoint_every=env_steps)
    spec_path = workdir / f"{study}.yaml"
    spec_path.write_text(yaml.safe_dump(spec))
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    if address is not None:
        env.update(HEAD_ENV)
    start_wall = time.time()
    start = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-m", "sweeper.cli", "launch", str(spec_path)]
        + (["--address", address] if address else []),
        cwd=workdir,
        env=env,
        capture_output=True,
        text=True,
        timeout=3600,
    )
    wall = time.perf_counter() - start
    if result.returncode != 0:
        sys.exit(f"sweeper launch failed (exit {result.returncode}):\n{result.stderr}")
    storage = f"sqlite:///{workdir / 'runs' / study / 'study.db'}"
    done = optuna.load_study(study_name=study, storage=storage).get_trials(deepcopy=False)
    complete = [t for t in done if t.state == optuna.trial.TrialState.COMPLETE]
    if len(complete) != trials:
        sys.exit(f"expected {trials} complete trials, found {len(complete)}")
    in_trials = sum(float(t.user_attrs["seconds"]) for t in complete)
    first_start = min(t.datetime_start.timestamp() for t in complete)
    last_end = max(t.datetime_complete.timestamp() for t in complete)
    by_start = sorted(complete, key=lambda t: t.datetime_start)
    gaps = [
        (t.datetime_complete - t.datetime_start).total_seconds() - float(t.user_attrs["seconds"])
        for t in by_start
    ]
    later = gaps[concurrency:] or [float("nan")]
    spans = [(t.datetime_start.timestamp(), t.datetime_complete.timestamp()) for t in complete]
    return {
        "concurrency": concurrency,
        "wall": wall,
        "in_trials": in_trials,
        "outside": 1.0 - covered_seconds(spans) / wall,
        "overhead": 1.0 - in_trials / (concurrency * wall),
        "startup": first_start - start_wall,
        "tail": start_wall + wall - last_end,
        "steady": 1.0 - in_trials / (concurrency * (last_end - first_start)),
        "gap_first": sum(gaps[:concurrency]) / len(gaps[:concurrency]),
        "gap_later": sum(later) / len(later),
    }


def covered_seconds(spans: list[tuple[float, float]]) -> float:
    """The length of the union of ``(start, end)`` intervals."""
    covered, reach = 0.0, float("-inf")
    for start, end in sorted(spans):
        if end > reach:
            covered += end - max(start, reach)
            reach = end
    return covered


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=4, help="trials in the study (default 4)")
    parser.add_argument(
        "--env-steps", type=int, default=5000, help="env steps per trial (default 5000)"
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="runs per concurrency, interleaved; figures are medians (default 1)",
    )
    parser.add_argument(
        "--ray",
        choices=("both", "head", "local"),
        default="both",
        help="head: every launch joins one `ray start --head` that the benchmark starts first "
        "(a one-node cluster: what a launch on a running cluster pays); local: every launch "
        "starts and stops its own Ray; both (default): head, then local",
    )
    parser.add_argument(
        "--address",
        metavar="ADDR",
        help="run on the Ray cluster already at ADDR instead (leaves out --ray)",
    )
    args = parser.parse_args()
    print(
        f"studies/ci.yaml (point_reach 32x32) as pixel only, {args.trials} trials x "
        f"{args.env_steps} env steps, {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f} (other work on the CPUs skews every figure)"
    )
    modes = ["head", "local"] if args.ray == "both" else [args.ray]
    if args.address:
        modes = [args.address]
    with tempfile.TemporaryDirectory(prefix="bench_concurrency_") as tmp:
        for mode in modes:
            if mode == "head":
                with ray_head(Path(tmp)) as address:
                    measure(Path(tmp), args, f"a running one-node Ray ({address})", address)
            else:
                address = None if mode == "local" else mode
                what = "its own local Ray each launch" if address is None else address
                measure(Path(tmp), args, what, address)
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")


def measure(tmp: Path, args: argparse.Namespace, what: str, address: str | None) -> None:
    """Run the study at c = 1 and c = 2 (``args.repeat`` times each) and print the figures."""
    print(f"\n== Ray: {what}")
    runs: dict[int, list[dict[str, float]]] = {1: [], 2: []}
    for repeat in range(args.repeat):
        for concurrency in runs:
            workdir = Path(tempfile.mkdtemp(prefix=f"c{concurrency}_{repeat}_", dir=tmp))
            row = run_study(workdir, args.trials, args.env_steps, concurrency, address)
            runs[concurrency].append(row)
            print_row(f"c={concurrency}", row)
    rows = [{k: statistics.median(r[k] for r in runs[c]) for k in runs[c][0]} for c in runs]
    if args.repeat > 1:
        for row in rows:
            print_row(f"median c={row['concurrency']:.0f}", row)
    speedup = rows[0]["wall"] / rows[1]["wall"]
    print(f"speed-up c=2 vs c=1: {speedup:.2f}x")
    outside = max(row["outside"] for row in rows)
    worst = max(row["overhead"] for row in rows)
    steady = max(row["steady"] for row in rows)
    print(
        f"time outside trials / total: max {100 * outside:.1f}% (target < 5%); idle trial "
        f"slots: max {100 * worst:.1f}% in all, {100 * steady:.1f}% while trials run"
    )
    for row in rows:
        fixed = row["startup"] + row["tail"]
        minutes = break_even_minutes(fixed, row["steady"])
        verdict = (
            f"idle slots under 5% for studies longer than {minutes:.1f} min"
            if minutes is not None
            else "not under 5% at any length (steady >= 5%)"
        )
        print(f"c={row['concurrency']:.0f}: fixed start-up + tail {fixed:.1f} s; {verdict}")


@contextlib.contextmanager
def ray_head(tmp: Path) -> Iterator[str]:
    """`ray start --head` as docs/cluster.md starts it, on a free port and with token
    authentication; yields its address, then stops it (only it: `ray stop` would stop every
    Ray on the machine)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    ray_cli, cpus = Path(sys.executable).with_name("ray"), os.cpu_count()
    log_path = tmp / "ray_head.log"
    log = log_path.open("w")
    head = subprocess.Popen(
        [str(ray_cli), "start", "--head", "--block", f"--port={port}", f"--num-cpus={cpus}"],
        env={**os.environ, **HEAD_ENV},
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 60
        while "Ray runtime started" not in log_path.read_text():
            if head.poll() is not None or time.monotonic() > deadline:
                sys.exit(f"ray start --head failed:\n{log_path.read_text()}")
            time.sleep(0.2)
        yield f"127.0.0.1:{port}"
    finally:
        head.terminate()
        head.wait(timeout=60)
        log.close()


def print_row(label: str, row: dict[str, float]) -> None:
    print(
        f"{label}: wall {row['wall']:6.1f} s | in trials {row['in_trials']:6.1f} s"
        f" | outside {100 * row['outside']:4.1f}% | idle slots {100 * row['overhead']:4.1f}%"
        f" | startup {row['startup']:4.1f} s"
        f" | tail {row['tail']:4.1f} s | steady {100 * row['steady']:4.1f}%"
        f" | gap {row['gap_first']:4.1f} s first, {row['gap_later']:4.2f} s later",
        flush=True,
    )


def break_even_minutes(fixed: float, steady: float, target: float = 0.05) -> float | None:
    """The wall time (minutes) from which ``fixed`` seconds plus a ``steady`` share of the
    rest stay under ``target``: solve ``fixed / W + steady * (1 - fixed / W) = target``."""
    if steady >= target:
        return None
    return fixed * (1.0 - steady) / (target - steady) / 60.0


if __name__ == "__main__":
    main()
