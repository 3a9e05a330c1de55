"""``sweeper rerun SPEC KEY``: run one recorded trial again from its plan entry and say
whether its curve is the recorded one, exactly.

A published study promises that anyone can re-run any of its trials bit-exactly. The
trial runs here in this process, with the parameters and seed its plan entry gives,
without a checkpoint, a video or a write to the study (which is read read-only), and every
metric at every evaluation step is compared with the recorded curve as floats, not to a
tolerance. A trial is bit-exact on the machine it ran on, not across machines (PyTorch's
CPU kernels round differently by vendor and instruction set: ``agent.machine``), so the
machines each run of the trial was recorded on are shown beside this one: a difference on
another machine is expected, on the same machine it is a bug. The convolutions run in the
layout the trial's record names, whatever this CPU would choose (``agent.machine.conv_layout``).

With ``--restore-videos`` the trial films its videos again, and where its curve is the
recorded one exactly (so its episodes are the recorded ones), each video the trial's
record names but the study's artifact store lacks is written there under its recorded id:
a published study whose video files were lost gets them back without a change to its
database. On another machine the curve differs and nothing is written: the run stops at
the first evaluation that differs (a trial costs up to hours, and the videos can only come
from a run that repeats it), where without ``--restore-videos`` it runs on to show the curve.

Exit codes: 0 the same curve, 1 another curve, 2 the study, key or trial cannot be used.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import math
import os
import sys
import time
from typing import TYPE_CHECKING, Any
from unittest import mock

from sweeper.plan import CONFIRM, PlanEntry, build_plan, confirm_plan
from sweeper.spec import plural, positive_int
from sweeper.storage import (
    ArtifactStore,
    NoStudy,
    artifact_location,
    artifacts_in,
    check_plan,
    current_trials,
    curve_of,
    describe_machine,
    open_for_reading,
    redact,
    stored_files,
    trial_attr,
)

if TYPE_CHECKING:
    from sweeper.spec import StudySpec


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The key of the trial to re-run (``sweeper.cli`` adds the spec and --storage)."""
    parser.add_argument("key", help="the trial's plan key, e.g. pixel/0/1 (method/config/seed)")
    parser.add_argument(
        "--restore-videos",
        action="store_true",
        help="film the trial again and, if its curve is the recorded one exactly, write the "
        "videos its record names that the study's artifact store is missing",
    )
    parser.add_argument(
        "--threads",
        type=positive_int,
        metavar="N",
        help="torch threads for the re-run (default: those of the trial's record; for a trial "
        "recorded before threads were, the spec's execution.threads_per_trial)",
    )


def first_difference(recorded: dict[str, list[float]], rerun: dict[str, list[float]]) -> str | None:
    """Where two curves (``{"step": [...], metric: [...]}``) first differ, in words, or
    None when every metric is the same float at every step (NaN equals NaN: a diverged
    trial's filler). Only the recorded steps and metrics are compared."""
    if list(rerun.get("step", [])) != list(recorded["step"]):
        return f"evaluation steps {rerun.get('step')} instead of the recorded {recorded['step']}"
    for index, step in enumerate(recorded["step"]):
        for metric in sorted(set(recorded) - {"step"}):
            want = float(recorded[metric][index])
            if metric not in rerun:
                return f"no {metric} (recorded: {want!r})"
            got = float(rerun[metric][index])
            if got != want and not (math.isnan(got) and math.isnan(want)):
                return f"step {step}, {metric}: {got!r} (recorded: {want!r})"
    return None


def difference_at(
    recorded: dict[str, list[float]], step: int, metrics: dict[str, float]
) -> str | None:
    """Where one evaluation (``step``, its ``metrics``) differs from the recorded curve's
    at that step, in words (``first_difference``'s), or None when it is the same."""
    if step not in recorded["step"]:
        return f"evaluation step {step}, which the record does not hold"
    index = recorded["step"].index(step)
    return first_difference(
        {metric: [values[index]] for metric, values in recorded.items()},
        {"step": [step], **{metric: [value] for metric, value in metrics.items()}},
    )


class _AnotherCurve(Exception):
    """Raised by the report at the first difference when the run can restore nothing."""


#: the conv layout of a record from before it was recorded: all code ran channels-last then
OLDER_LAYOUT = "channels_last"


def recorded_layout(recorded: list[dict[str, Any]] | None) -> str:
    """The conv layout the trial's first recorded run used (``OLDER_LAYOUT`` for a run or
    trial recorded before layouts were): the one a re-run must use to repeat its sums."""
    return (recorded or [{}])[0].get("conv_layout", OLDER_LAYOUT)


def recorded_threads(recorded: list[dict[str, Any]] | None, spec_threads: int) -> int:
    """The torch threads of the trial's first recorded run (``spec_threads``, the spec's
    ``execution.threads_per_trial``, for one recorded before threads were): the number a
    re-run must use to split its sums the same way."""
    return int((recorded or [{}])[0].get("threads", spec_threads))


def machine_lines(recorded: list[dict[str, Any]] | None, here: dict[str, Any]) -> list[str]:
    """The machines the trial's runs were recorded on, this one, and what follows."""
    recorded = recorded or []
    lines = [f"recorded on: {describe(m)} (from step {m['from_step']})" for m in recorded]
    if not recorded:
        lines.append("recorded on: not recorded (the study ran before machines were recorded)")
    elif recorded[0]["from_step"] != 0:
        lines.append(f"the runs before step {recorded[0]['from_step']} were not recorded")
    lines.append(f"this machine: {describe(here)}")
    whole = bool(recorded) and recorded[0]["from_step"] == 0
    # a record from before layouts or threads were recorded: channels-last, threads unknown
    was = [{"conv_layout": OLDER_LAYOUT, "threads": here.get("threads"), **m} for m in recorded]
    unthreaded = any("threads" not in m for m in recorded)
    if whole and all({k: v for k, v in m.items() if k != "from_step"} == here for m in was):
        if unthreaded:
            threads = plural(int(here["threads"]), "torch thread")
            lines.append(f"the same machine if the trial ran at {threads}, as this re-run does "
                         "(its threads were not recorded; --threads sets the re-run's): then "
                         "the curve should be the recorded one")  # fmt: skip
        else:
            lines.append("the same machine: the curve should be the recorded one")
    else:
        lines.append("another machine (or unknown): PyTorch's kernels round differently there, "
                     "so the curve may differ (agent/machine.py)")  # fmt: skip
    return lines


#: one line for a machine: CPU name and id, kernels, torch, GPU
describe = describe_machine


def run(spec: StudySpec, args: argparse.Namespace) -> int:
    """``sweeper rerun``: exit 0 (the same curve), 1 (another) or 2 (cannot be done)."""
    try:
        entry, trial = _recorded(spec, args.key)
    except ValueError as e:  # StorageError, NoStudy, an unknown key or an unfinished trial
        print(f"sweeper rerun: {e}", file=sys.stderr)
        return 2
    recorded = curve_of(trial)
    if trial.state.name == "WAITING":
        print(f"sweeper rerun: {args.key} has not started yet: nothing to compare with",
              file=sys.stderr)  # fmt: skip
        return 2
    if trial.state.name not in ("COMPLETE", "PRUNED") or not recorded:
        print(
            f"sweeper rerun: {args.key} is not done (trial {trial.number} is "
            f"{trial.state.name}): there is no finished curve to compare with",
            file=sys.stderr,
        )
        return 2

    import torch

    import agent
    from agent.machine import LAYOUT_VARIABLE
    from agent.machine import describe as this_machine
    from encoders.torch_base import resolve_device

    config = entry.trial_config
    last = recorded["step"][-1]
    config = dataclasses.replace(
        config,
        checkpoint_dir=None,
        video_steps=config.video_steps if args.restore_videos else (),
        stop_at=last if last < config.total_steps else None,  # a trial halving stopped
    )
    videos: dict[str, bytes] = {}
    machines = trial_attr(trial, "machines")
    # the recorded layout and threads (unless --threads), not this CPU's choice or the
    # spec's: both order sums
    layout = recorded_layout(machines)
    threads = args.threads or recorded_threads(machines, config.threads)
    config = dataclasses.replace(config, threads=threads)
    torch.set_num_threads(config.threads)
    here = {**this_machine(resolve_device(config.device)), "conv_layout": layout}
    print(f"study {spec.study!r} in {redact(spec.storage_url)}: {args.key} (trial {trial.number})")
    print("\n".join(machine_lines(machines, here)))
    print(f"re-running {config.total_steps if last == config.total_steps else last} env steps "
          f"of {config.method} on {config.env} ...", flush=True)  # fmt: skip
    start = time.perf_counter()

    differences: list[str] = []

    def report(step: int, metrics: dict[str, float]) -> None:
        index = recorded["step"].index(step) if step in recorded["step"] else None
        want = recorded["success_rate"][index] if index is not None else float("nan")
        print(
            f"  step {step:>7}: success {metrics['success_rate']:.2f} (recorded {want:.2f}), "
            f"{time.perf_counter() - start:.0f} s",
            flush=True,
        )
        difference = None if differences else difference_at(recorded, step, metrics)
        if difference is not None:
            differences.append(difference)
            print(f"  another curve from here: {difference}", flush=True)
            if args.restore_videos:
                raise _AnotherCurve(difference)

    film = videos.__setitem__ if args.restore_videos else None
    try:
        with mock.patch.dict(os.environ, {LAYOUT_VARIABLE: layout}):
            result = agent.train(config, report, film)
    except _AnotherCurve as e:
        print(f"another curve: first difference at {e}\nstopped there: this run's episodes "
              "are not the recorded ones, so no video can be restored from them")  # fmt: skip
        return 1
    except (ValueError, OSError) as e:  # e.g. vgg's weights file is not on this machine
        print(f"sweeper rerun: {args.key} cannot run here: {e}", file=sys.stderr)
        return 2
    curve = {"step": list(result.steps), **{k: list(v) for k, v in result.metrics.items()}}
    difference = first_difference(recorded, curve)
    if difference is None:
        print(f"the same curve: every metric at all {plural(len(recorded['step']), 'step')} "
              "is the recorded float")  # fmt: skip
        if args.restore_videos:
            print("\n".join(restore_videos(spec, trial, videos)))
        return 0
    print(f"another curve: first difference at {difference}")
    if args.restore_videos:
        print("videos not restored: this run's episodes are not the recorded ones")
    return 1


def restore_videos(spec: StudySpec, trial: Any, videos: dict[str, bytes]) -> list[str]:
    """Write each of ``trial``'s recorded videos that the study's artifact store lacks,
    from ``videos`` (file name -> bytes, filmed by a run with the recorded curve), under
    its recorded artifact id; one line per video of the record."""
    import io

    from optuna.artifacts.exceptions import ArtifactNotFound

    store = ArtifactStore(artifact_location(spec))
    metas = artifacts_in(trial.system_attrs)
    lines = []
    for meta in sorted(metas, key=lambda meta: meta["filename"]):
        name, artifact_id = meta["filename"], meta["artifact_id"]
        try:
            store.open_reader(artifact_id).close()
            lines.append(f"video {name}: present ({artifact_id}), left as it is")
            continue
        except ArtifactNotFound:
            pass
        if name not in videos:
            lines.append(f"video {name}: missing, and this run filmed no such episode")
            continue
        store.write(artifact_id, io.BytesIO(videos[name]))
        lines.append(f"video {name}: restored to {store.location}/{artifact_id}")
    return lines or ["the trial's record names no video"]


def _recorded(spec: StudySpec, key: str) -> tuple[PlanEntry, Any]:
    """The plan entry of ``key`` (a search or confirmation key) and its current trial;
    ValueError when the study, the key or its trial does not exist."""
    with open_for_reading(spec) as store:
        if isinstance(store, NoStudy):
            raise store
        search = build_plan(stored_files(spec, store))
        check_plan(spec.study, store.attrs, search.hash)
        plans = [search]
        confirm = store.attrs.get(CONFIRM)
        if confirm:
            configs = {m: [int(c) for c in ids] for m, ids in confirm["configs"].items()}
            plans.append(confirm_plan(search, configs, tuple(confirm["seeds"])))
        entries = {e.key: e for plan in plans for e in plan.entries}
        if key not in entries:
            close = difflib.get_close_matches(key, entries, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise ValueError(f"{key!r} is not a key of study {spec.study!r}{hint}")
        trial = current_trials(store.trials()).get(key)
    if trial is None:
        raise ValueError(f"{key} has not run yet in study {spec.study!r}")
    return entries[key], trial
