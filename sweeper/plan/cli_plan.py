"""``sweeper plan SPEC``: the plan before anything runs, and what it will cost here.

Per method: its trials, their env steps, how many are done, and one trial's estimated wall
time (``sweeper.plan._estimate``: from the study's finished trials of that method when the study
exists, else calibrated on this machine in a few seconds). Then the study's total trial time
and its wall time at the spec's concurrency on this machine. Reads the study read-only and
needs no training-only file: a method whose file is missing here (VGG's weights) is listed
with its cost unknown.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from fractions import Fraction
from typing import TYPE_CHECKING, TextIO

from sweeper.plan._entries import A1, A1_SAMPLES, Plan, PlanEntry, build_plan, outside_a1
from sweeper.plan._estimate import (
    TrialEstimate,
    estimate_trials,
    format_duration,
    halving_seconds,
    machine_at,
    summary_lines,
)
from sweeper.plan._halving import env_steps_spent
from sweeper.spec import plural, positive_int
from sweeper.storage import (
    NoStudy,
    check_plan,
    finished,
    open_for_reading,
    redact,
    stored_files,
)

if TYPE_CHECKING:
    from sweeper.spec import StudySpec


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sweeper plan`` (the spec and ``--storage`` come from ``sweeper.cli``):
    ``sweeper launch``'s execution overrides, so the estimate is the launch's."""
    parser.add_argument("--max-concurrent", metavar="N", type=positive_int, help="trials at once")
    parser.add_argument(
        "--threads-per-trial",
        metavar="N",
        type=positive_int,
        help="as `sweeper launch --threads-per-trial`: trials measured at these threads are "
        "taken, the others calibrated at them",
    )


def plan_lines(
    spec: StudySpec, plan: Plan, done: set[str], measured: dict[str, float]
) -> list[str]:
    """The plan table and the estimate (calibrating the methods without finished trials).
    A method whose file is missing here (``StudySpec.missing_files``: vgg without its
    weights) is listed with its cost unknown and left out of the totals."""
    needs = {item.method: item for item in spec.missing_files()}
    known = [e for e in plan.entries if e.method not in needs or e.method in measured]
    start = time.perf_counter()
    estimates = estimate_trials(known, measured)
    calibration_seconds = time.perf_counter() - start
    steps = spec.budget.env_steps
    lines = [
        f"study {spec.study!r}: {plural(len(spec.methods), 'method')} x "
        f"{plural(spec.trials_per_method, 'configuration')} x {plural(len(spec.seeds), 'seed')} "
        f"= {plural(len(plan.entries), 'trial')} of {steps:,} env steps "
        f"({len(plan.entries) * steps:,} in all)"
    ]
    width = max(len("method"), *(len(m) for m in spec.methods))
    lines.append(
        f"{'method':<{width}}  {'trials':>6}  {'env steps':>11}  {'done':>4}  "
        f"{'one trial':>13}  from"
    )
    for method in spec.methods:
        entries = [e for e in plan.entries if e.method == method]
        finished = sum(e.key in done for e in entries)
        if entries[0].key in estimates:
            mean = sum(estimates[e.key].seconds for e in entries) / len(entries)
            cost, source = format_duration(mean), estimates[entries[0].key].source
            if source == "measured":
                source = f"measured ({finished} finished)"
        else:
            cost, source = "unknown", f"needs its file: {needs[method].at}: {needs[method].message}"
        lines.append(
            f"{method:<{width}}  {len(entries):>6}  {len(entries) * steps:>11,}  "
            f"{finished:>4}  {cost:>13}  {source}"
        )
    lines += budget_lines(spec, plan)
    lines += precision_lines(spec, [e for e in known if e.key in estimates], estimates)
    if plan.schedule is not None:
        lines += halving_lines(replace(plan, entries=tuple(known)), estimates, len(spec.seeds))
    lines += summary_lines(known, done, estimates, spec.execution, calibration_seconds)
    unknown = [m for m in spec.methods if m not in {e.method for e in known}]
    if unknown:
        count = sum(e.method in unknown for e in plan.entries)
        lines.append(
            f"not counted above: {', '.join(unknown)} ({plural(count, 'trial')}), whose cost "
            "is unknown until the file it needs is given (sweeper launch refuses the study "
            "without it, or runs the other methods with --skip-missing)"
        )
    return lines


def budget_lines(spec: StudySpec, plan: Plan) -> list[str]:
    """Each method's gradient samples per env step (batch x updates per step) against
    appendix A.1's, and the SAC values outside A.1: the study's constants once, each
    method's own fixed values (``methods.<name>.sac``) and the constants some method
    replaces on each method's line."""
    lines = [
        f"gradient samples per env step (batch x updates per step; A.1: {A1.batch_size} x "
        f"{A1.updates_per_step} = {A1_SAMPLES}):"
    ]
    constants = {k: cs[0] for k, cs in spec.sac.space().items() if len(cs) == 1}
    # a constant some method replaces is said per method, the others once for all
    replaced = {name for m in spec.methods.values() for name in m.sac}
    shared = outside_a1({k: v for k, v in constants.items() if k not in replaced})
    width = max(len(m) for m in spec.methods)
    for method in spec.methods:
        configs = [e.trial_config.sac for e in plan.entries if e.method == method]
        samples = sorted({c.batch_size * c.updates_per_step for c in configs})
        shown = " | ".join(
            f"{c.batch_size} x {c.updates_per_step} = {c.batch_size * c.updates_per_step}"
            for c in {(c.batch_size, c.updates_per_step): c for c in configs}.values()
        )
        fraction = " | ".join(
            "all" if n == A1_SAMPLES else str(Fraction(n, A1_SAMPLES)) for n in samples
        )
        fixed = {k: v for k, v in constants.items() if k in replaced}
        own = outside_a1(fixed | spec.methods[method].sac)
        mark = f"; outside A.1: {', '.join(own)}" if own else ""
        lines.append(f"  {method:<{width}}  {shown}  ({fraction} of A.1){mark}")
    if shared:
        lines.append(f"  every method, outside A.1: {', '.join(shared)}")
    return lines


def precision_lines(
    spec: StudySpec, entries: list[PlanEntry], estimates: dict[str, TrialEstimate]
) -> list[str]:
    """The update's precision; for bf16 on CPU trials on a CPU without native bf16 (no AMX,
    no AVX512-BF16), a warning with how much slower one trial is than in fp32 here (its
    first calibrated entry calibrated again in fp32)."""
    from agent import machine  # here: `sweeper plan --help` imports no torch

    if spec.precision == "fp32":
        return ["precision: fp32"]
    lines = ["precision: bf16 autocast (weights, optimiser state, targets and rewards fp32)"]
    calibrated = [e for e in entries if estimates[e.key].source == "calibrated"]
    if spec.execution.gpus_per_trial or machine.native_bf16() or not calibrated:
        return lines
    entry = calibrated[0]
    fp32 = replace(entry, trial_config=replace(entry.trial_config, precision="fp32"))
    ratio = estimates[entry.key].seconds / estimate_trials([fp32], {})[entry.key].seconds
    lines.append(
        f"warning: this CPU has no native bf16 (no AMX, no AVX512-BF16): a {entry.method} "
        f"trial in bf16 takes {ratio:.1f}x its time in fp32 here; set precision: fp32"
    )
    return lines


def halving_lines(plan: Plan, estimates: dict[str, TrialEstimate], seeds: int) -> list[str]:
    """Each rung's trials per method, and what the halving spends against the full plan
    (the table above and the lines below count every trial to the full budget)."""
    schedule = plan.schedule
    methods = len({e.method for e in plan.entries})
    lines = [
        f"halving ({schedule.rule}, keep {schedule.keep:.2f}): every method runs the same "
        "trials to each stop:"
    ]
    for stop, size in zip(schedule.stops, schedule.sizes, strict=True):
        lines.append(
            f"  to step {stop:>11,}: {plural(size, 'configuration')} x {plural(seeds, 'seed')} "
            f"per method, {plural(size * seeds * methods, 'trial')}"
        )
    spent = env_steps_spent(schedule.stops, schedule.sizes, seeds)
    full = len(plan.entries) // methods * schedule.stops[-1]
    with_halving = halving_seconds(plan.entries, estimates, schedule)
    without = sum(e.seconds for e in estimates.values())
    lines.append(
        f"  env steps per method: {spent:,} of {full:,} without halving ({spent / full:.0%}); "
        f"trial time about {format_duration(with_halving)} of {format_duration(without)}"
    )
    return lines


def run(spec: StudySpec, args: argparse.Namespace, stream: TextIO | None = None) -> int:
    """``sweeper plan``: print the plan and its estimate; exit 0, or 2 when the study
    cannot be read or was launched with another plan."""
    stream = sys.stdout if stream is None else stream
    try:
        spec = spec.with_overrides(
            max_concurrent=args.max_concurrent, threads_per_trial=args.threads_per_trial
        )
        with open_for_reading(spec) as store:
            spec = stored_files(spec, store)  # a file path the study was launched with
            plan = build_plan(spec)
            done, measured = set(), {}
            if not isinstance(store, NoStudy):
                check_plan(spec.study, store.attrs, plan.hash)
                here = machine_at(spec.execution.threads_per_trial)
                done, measured = finished(store.trials(), plan.keys(), here)
    except ValueError as e:  # StorageError, a plan the spec cannot give
        print(f"sweeper plan: {e}", file=sys.stderr)
        return 2
    print(f"study {spec.study!r} in {redact(spec.storage_url)}", file=stream)
    print("\n".join(plan_lines(spec, plan, done, measured)), file=stream)
    return 0
