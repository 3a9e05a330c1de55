"""``sweeper plan SPEC``: the plan before anything runs, and what it will cost here.

Per method: its trials, their env steps, how many are done, and one trial's estimated wall
time (``sweeper.estimate``: from the study's finished trials of that method when the study
exists, else calibrated on this machine in a few seconds). Then the study's total trial time
and its wall time at the spec's concurrency on this machine. Reads the study read-only and
needs no training-only file (VGG is timed with random weights).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import TYPE_CHECKING, TextIO

from sweeper.estimate import (
    CPU_WARNING_SECONDS,
    estimate_trials,
    format_duration,
    local_workers,
    makespan,
    measured_seconds,
)
from sweeper.plan import Plan, build_plan, run_order
from sweeper.storage import current_trials, redact
from sweeper.study import NoStudy, open_study

if TYPE_CHECKING:
    from sweeper.spec import StudySpec


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``sweeper plan`` has no options of its own (``sweeper.cli`` adds the spec and
    --storage)."""


def finished(spec: StudySpec, plan: Plan) -> tuple[set[str], dict[str, float]]:
    """(keys done, per method the mean seconds of its finished trials) of the study, or
    nothing when it has not been launched; raises StorageError (a ValueError)."""
    try:
        with open_study(
            spec.storage_url, spec.study, write=False, plan_hash=plan.hash,
            grace=spec.execution.storage_grace,
        ) as store:  # fmt: skip
            current = current_trials(store.trials())
    except NoStudy:
        return set(), {}
    planned = set(plan.keys())
    done = {k for k, t in current.items() if k in planned and t.state.name == "COMPLETE"}
    seconds = [
        (k.split("/")[0], float(current[k].user_attrs["seconds"]))
        for k in done
        if current[k].user_attrs.get("seconds")
    ]
    return done, measured_seconds(seconds)


def plan_lines(
    spec: StudySpec, plan: Plan, done: set[str], measured: dict[str, float]
) -> list[str]:
    """The plan table and the estimate (calibrating the methods without finished trials)."""
    start = time.perf_counter()
    estimates = estimate_trials(plan.entries, measured)
    calibration_seconds = time.perf_counter() - start
    steps = spec.budget.env_steps
    lines = [
        f"study {spec.study!r}: {len(spec.methods)} methods x {spec.trials_per_method} "
        f"configurations x {len(spec.seeds)} seeds = {len(plan.entries)} trials of "
        f"{steps:,} env steps ({len(plan.entries) * steps:,} in all)"
    ]
    width = max(len("method"), *(len(m) for m in spec.methods))
    lines.append(
        f"{'method':<{width}}  {'trials':>6}  {'env steps':>11}  {'done':>4}  "
        f"{'one trial':>13}  from"
    )
    for method in spec.methods:
        entries = [e for e in plan.entries if e.method == method]
        mean = sum(estimates[e.key].seconds for e in entries) / len(entries)
        source = estimates[entries[0].key].source
        if source == "measured":
            count = sum(e.key in done for e in entries)
            source = f"measured ({count} finished)"
        lines.append(
            f"{method:<{width}}  {len(entries):>6}  {len(entries) * steps:>11,}  "
            f"{sum(e.key in done for e in entries):>4}  {format_duration(mean):>13}  {source}"
        )
    left = [e for e in sorted(plan.entries, key=run_order) if e.key not in done]
    trial_seconds = sum(estimates[e.key].seconds for e in left)
    execution = spec.execution
    workers = local_workers(execution.max_concurrent, execution.threads_per_trial)
    wall = makespan([estimates[e.key].seconds for e in left], workers)
    lines.append(
        f"left: {len(left)} of {len(plan.entries)} trials, {format_duration(trial_seconds)} of "
        f"trial time; about {format_duration(wall)} at {workers} trial(s) at once on this "
        f"machine ({os.cpu_count()} cores, {execution.threads_per_trial} thread(s) a trial)"
    )
    if any(e.source == "calibrated" for e in estimates.values()):
        load = os.getloadavg()[0]
        lines.append(
            f"calibrated in {format_duration(calibration_seconds)} here, at a load average "
            f"of {load:.1f}" + (": a busy machine gives slower figures" if load > 1 else "")
        )
    if execution.gpus_per_trial == 0 and trial_seconds > CPU_WARNING_SECONDS:
        lines.append(cpu_warning(trial_seconds))
    return lines


def cpu_warning(trial_seconds: float) -> str:
    """The warning for a plan of more than a day of CPU."""
    return (
        f"warning: this is {format_duration(trial_seconds)} of CPU trial time; on a cluster "
        "with GPUs set execution.gpus_per_trial (e.g. 0.25: four trials a GPU), see "
        "docs/cluster.md"
    )


def run(spec: StudySpec, args: argparse.Namespace, stream: TextIO | None = None) -> int:
    """``sweeper plan``: print the plan and its estimate; exit 0, or 2 when the study
    cannot be read or was launched with another plan."""
    stream = sys.stdout if stream is None else stream
    try:
        plan = build_plan(spec)
        done, measured = finished(spec, plan)
    except ValueError as e:  # StorageError, a plan the spec cannot give
        print(f"sweeper plan: {e}", file=sys.stderr)
        return 2
    print(f"study {spec.study!r} in {redact(spec.storage_url)}", file=stream)
    print("\n".join(plan_lines(spec, plan, done, measured)), file=stream)
    return 0
