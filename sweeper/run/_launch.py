"""The launch sequence of a study: from a spec to a claimed, synced study driven on Ray.

``prepare`` validates everything first (spec, env and encoder options, storage URL), and
``launch`` checks that the database can be written and read (an existing study is read,
its file checked for damage, an outage waited out for ``execution.storage_grace``) and
that Ray can be reached before it opens the study as its writer, so a bad input exits
with code 2 and writes nothing. A relaunch with every key done (``all_done``) exits 0
without starting Ray. Otherwise it sizes the worker pool to the cluster
(``sweeper.run._resources``), opens the study as its writer (a failure then, an outage past
the grace or a full disk, is one line too), claims it, gives every plan key that is not
done a WAITING trial (``StudyStore.sync``), measures the random agent once per study
(``sweeper.run._random_agent``), and hands the keys to the ``sweeper.run._driver.Driver`` loop.

Ctrl-C or SIGTERM, at any moment of a launch, stops the workers and marks the trials in
flight ``interrupted``; a relaunch resumes them from their checkpoints. Exit codes: 0 all
done, 1 some trials failed, 2 bad input, 3 another driver runs the study (busy), 130
interrupted. What trials print goes to Ray's worker logs (``/tmp/ray/session_latest/logs``),
not to the progress display.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Callable
from typing import Any, TextIO

import optuna

from agent.envs import env_class
from agent.metrics import metric_key
from sweeper.plan import (
    HALVING_ATTR,
    Curves,
    InBackground,
    Ladder,
    Plan,
    TrialEstimate,
    build_plan,
    in_spec_order,
    machine_at,
    run_order,
    summary_lines,
)
from sweeper.run import _random_agent as random_agent
from sweeper.run._execution import WorkerPool, start_ray, stop_ray
from sweeper.run._progress import LaunchProgress
from sweeper.run._resources import cannot_reach_message, local_cpus, pool_size
from sweeper.run._signals import Interrupted, stop_on_signals
from sweeper.spec import StudySpec, load_spec, plural
from sweeper.storage import (
    DONE_STATES,
    Heartbeat,
    NoStudy,
    StorageError,
    StudyBusy,
    StudyStore,
    check_storage,
    check_writable,
    code_revision,
    current_trials,
    curve_of,
    finished,
    ledger,
    open_study,
    package_versions,
    redact,
)

#: what a driver runs once it holds the study: its plan, bound to the study
Stage = Callable[[StudySpec, StudyStore], Plan]
#: seconds between the driver's heartbeats in the study
HEARTBEAT_SECONDS = 15.0
#: exit code of a launch refused because another live driver runs the study
EXIT_BUSY = 3
#: seconds each part of a trial is timed for the launch's estimate (``sweeper plan``
#: takes longer over it: 0.5 s)
CALIBRATION_SECONDS = 0.1


def prepare(
    spec: StudySpec | str | os.PathLike[str],
    storage: str | None = None,
    address: str | None = None,
    max_concurrent: int | None = None,
    threads_per_trial: int | None = None,
) -> tuple[StudySpec, Plan]:
    """Validate the spec (or the spec file) with its overrides, build its plan and check
    the storage.

    Raises ``SpecError`` or ``StorageError`` (both ValueErrors naming the field); writes
    nothing anywhere.
    """
    if not isinstance(spec, StudySpec):
        spec = load_spec(spec)
    spec = spec.with_overrides(
        storage=storage,
        address=address,
        max_concurrent=max_concurrent,
        threads_per_trial=threads_per_trial,
    )
    plan = build_plan(spec)
    check_storage(spec.storage_url)
    return spec, plan


def study_attrs(spec: StudySpec, plan: Plan) -> dict[str, Any]:
    """The study user attrs (docs/contracts.md, "Storage conventions")."""
    return {
        "spec": spec.model_dump(mode="json"),
        "plan_hash": plan.hash,
        "plan": plan.keys(),
        "versions": package_versions(),
        "revision": code_revision(),
        "env": spec.env.name,
        "metric_names": list(report_metric_names(spec.env.name)),
    }


def report_metric_names(env: str) -> tuple[str, ...]:
    """The metric keys a trial on ``env`` reports (docs/contracts.md, "One trial")."""
    return tuple(metric_key(name) for name in env_class(env).metric_names)


@dataclasses.dataclass
class Launch:
    """One launch, what each of its steps reads: the spec, the plan (whole: its hash is the
    study's), the methods it leaves out, where it prints, the stage it runs once it holds
    the study (None: the search plan), the workers' ``train`` (tests), the most trials it
    starts (None: all left) and the cost estimate running in the background (None: a
    stage, or none yet)."""

    spec: StudySpec
    plan: Plan
    skip: frozenset[str]
    stream: TextIO
    stage: Stage | None
    train: Callable[..., Any] | None
    max_trials: int | None = None
    estimate: InBackground | None = None

    @property
    def runs(self) -> Plan:
        """The plan's entries this launch runs (``skip``'s left out)."""
        return without(self.plan, self.skip)

    def say(self, line: str) -> None:
        print(line, file=self.stream)


def launch(
    spec: StudySpec,
    plan: Plan,
    *,
    train: Callable[..., Any] | None = None,
    stream: TextIO | None = None,
    stage: Stage | None = None,
    skip: frozenset[str] = frozenset(),
    max_trials: int | None = None,
) -> int:
    """Run (or resume) the study of a validated ``spec``; return the exit code.

    The database must be writable and Ray reachable before anything is written. A Ray that
    is already initialised is used and left running; otherwise one is started (local, or
    ``execution.address``) and shut down at the end. ``train`` replaces ``agent.train`` in
    the workers (tests). ``stage`` gives the plan to run once the study is claimed
    (default: the search plan; ``sweeper confirm``: the confirmation stage); a StorageError
    from it exits 2. ``skip``: methods this launch leaves out (``sweeper launch
    --skip-missing``, ``--only``): their keys are synced like the others, so they stay left
    in the ledger, and are not run; the plan, and its hash, stay whole. ``max_trials``
    (``--max-trials``): start at most that many of the trials left, in ``run_order``; the
    others stay left for a later launch. Ctrl-C and SIGTERM raise ``Interrupted`` throughout.
    """
    stream = sys.stderr if stream is None else stream
    run = Launch(spec, plan, skip, stream, stage, train, max_trials)
    with stop_on_signals():
        try:
            check_writable(spec.storage_url)
            study = read_study(spec, plan)
        except StorageError as e:
            run.say(f"sweeper launch: {e}")
            return 2
        if stage is None and all_done(spec, run.runs, study):  # nothing left: no Ray
            total = done = len(plan.entries)
            if skip and study is not None:  # the skipped keys an earlier launch ran count
                done = sum(c.done for c in ledger(plan.keys(), study[0], False).values())
            run.say(
                f"study {spec.study!r} in {redact(spec.storage_url)}: {done} of {total} "
                f"trials done, 0 to run{skipped_note(run)}"
            )
            return 0
        # the calibration runs while Ray and the workers start, but before them at more
        # than one thread a trial: two torch threads on two cores beside Ray starting timed
        # a 1/2 trial of 1 h 44 min at 3 h 25 min (docs/costs.md)
        threads = spec.execution.threads_per_trial
        run.estimate = None if stage is not None else start_estimate(run.runs, study, threads)
        try:
            if run.estimate is not None and threads > 1:
                run.estimate.result()
            return _start_ray_and_launch(run)
        finally:  # a launch that ends first (busy, interrupted, ...) ends the calibration
            if run.estimate is not None:
                run.estimate.stop()


def _start_ray_and_launch(run: Launch) -> int:
    """Connect to Ray (starting a local one unless ``execution.address`` names a cluster),
    run the study on it, and shut down a Ray this call started."""
    address = run.spec.execution.address
    try:
        started_ray = start_ray(address, num_cpus=local_cpus(run.spec.execution))
    except SystemExit:  # Ray's own SIGTERM handlers, set while it starts, exit this way
        stop_ray()
        raise Interrupted() from None
    except Exception as e:  # ConnectionError, an auth error, ...
        run.say(cannot_reach_message(address, e))
        return 2
    try:
        return _launch_on_ray(run)
    finally:
        if started_ray:
            stop_ray()


def read_study(spec: StudySpec, plan: Plan) -> tuple[list[Any], dict[str, Any]] | None:
    """The study's trials and user attrs, read read-only before Ray starts; None when there
    is nothing to read yet (``NoStudy``). Raises StorageError when the database cannot be
    used (damaged, launched with another plan, out for longer than the grace)."""
    try:
        with open_study(
            spec.storage_url,
            spec.study,
            write=False,
            plan_hash=plan.hash,
            grace=spec.execution.storage_grace,
        ) as store:
            return store.trials(), store.attrs
    except NoStudy:
        return None


def all_done(spec: StudySpec, plan: Plan, study: tuple[list[Any], dict[str, Any]] | None) -> bool:
    """Whether the study (``read_study``) holds every key of ``plan`` done, and its random
    agent measured if the spec asks for it."""
    if study is None:
        return False
    trials, attrs = study
    if spec.random_episodes and random_agent.ATTR not in attrs:
        return False
    return all(c.done == c.planned for c in ledger(plan.keys(), trials, False).values())


def _launch_on_ray(run: Launch) -> int:
    """Size the worker pool to the Ray cluster, start it and run the study."""
    execution = run.spec.execution
    size = pool_size(execution, len(run.runs.entries), run.stream)
    if size is None:
        return 2
    # the workers start (importing torch and the env) while the driver opens the study
    pool = WorkerPool(
        size,
        cpus=execution.cpus_per_trial,
        gpus=execution.gpus_per_trial,
        train=run.train,
        env=run.spec.env.name,
        stall_timeout=execution.stall_timeout,
    )
    try:
        return _run_study(run, pool)
    finally:
        pool.shutdown()


def _run_study(run: Launch, pool: WorkerPool) -> int:
    """Open the study as its driver, its heartbeat beating until it lets go; run it."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    spec = run.spec
    attrs = study_attrs(spec, run.plan)
    grace = spec.execution.storage_grace
    try:
        with open_study(
            spec.storage_url, spec.study, write=True, attrs=attrs, grace=grace
        ) as store:
            try:
                store.claim_driver()
            except StudyBusy as e:
                run.say(f"sweeper launch: {e}")
                return EXIT_BUSY
            try:
                with store.heartbeats(HEARTBEAT_SECONDS) as beat:
                    if store.attrs.get("revision") != attrs["revision"]:
                        run.say(
                            f"sweeper launch: note: the study began at code revision "
                            f"{store.attrs.get('revision')}; this is {attrs['revision']}"
                        )
                    return _sync_and_drive(run, store, pool, beat)
            except StorageError as e:  # the stage cannot be run (sweeper confirm)
                run.say(f"sweeper {'launch' if run.stage is None else 'confirm'}: {e}")
                return 2
            except StudyBusy as e:  # a heartbeat found another driver: this one looked dead
                run.say(f"sweeper launch: stopped: {e}")
                return EXIT_BUSY
            finally:
                store.release_driver()
    except StorageError as e:  # opening or creating the study
        run.say(f"sweeper launch: {e}")
        return 2


def _sync_and_drive(run: Launch, store: StudyStore, pool: WorkerPool, beat: Heartbeat) -> int:
    """Give the plan's keys their trials, then run what is left (but ``skip``'s)."""
    spec, skip = run.spec, run.skip
    # bound to the study: its checkpoints are its own
    if run.stage is None:
        plan = build_plan(spec, study_uid=store.study_uid)
    else:
        plan = run.stage(spec, store)
    run = dataclasses.replace(run, plan=plan)
    todo = store.sync(plan.entries, plan.hash)
    skipped = sum(entry.method in skip for entry, _ in todo)
    todo = sorted(
        ((entry, trial) for entry, trial in todo if entry.method not in skip),
        key=lambda item: run_order(item[0]),
    )
    later = todo[run.max_trials :] if run.max_trials is not None else []
    todo = todo[: len(todo) - len(later)]
    random_agent.record_random_agent(spec, store, run.stream)
    total = len(plan.entries)
    run.say(
        f"study {spec.study!r} in {redact(spec.storage_url)}: "
        f"{total - len(todo) - len(later) - skipped} of {total} trials done, "
        f"{len(todo)} to run{skipped_note(run)}"
        + (f"; {len(later)} more left for a later launch (--max-trials)" if later else "")
    )
    if not todo:
        return 0
    pool.shrink(len(todo))
    not_now = {entry.key for entry, _ in later}  # not this launch's: not in its estimate
    estimates = None if run.estimate is None else print_estimate(run, not_now)
    keys = [entry.key for entry in run.runs.entries if entry.key not in not_now]
    progress = LaunchProgress(
        spec.study, in_spec_order(keys, spec.methods),
        spec.budget.env_steps, run.stream,
        estimates=estimates, workers=len(pool),
    )  # fmt: skip
    ladder, curves = halving_state(plan, store)
    # here, not at the top: the driver loads all it runs (torch, the dashboard's figures)
    # before its loop, and ``prepare`` (spec checks) stays without them
    from sweeper.run._driver import Driver

    return Driver(spec, store, pool, progress, beat, run.stream, ladder, curves).run(todo)


def halving_state(plan: Plan, store: StudyStore) -> tuple[Ladder | None, Curves]:
    """A plan with successive halving: its ladder, with the decisions the study holds, and
    the curves of its done keys (what later decisions read with the new ones)."""
    if plan.schedule is None:
        return None, {}
    entries = plan.entries
    ladder = Ladder(
        plan.schedule,
        configs={e.config_id for e in entries},
        seeds={e.seed for e in entries},
        methods={e.method for e in entries},
        decisions=store.attrs.get(HALVING_ATTR),
    )
    planned = {e.key: e for e in entries}
    curves = {}
    for key, trial in current_trials(store.trials()).items():
        curve = curve_of(trial)
        if key in planned and trial.state.name in DONE_STATES and curve:
            entry = planned[key]
            curves[(entry.method, entry.config_id, entry.seed)] = (
                curve["step"],
                curve["success_rate"],
            )
    return ladder, curves


def without(plan: Plan, skip: frozenset[str]) -> Plan:
    """``plan`` without the entries of the methods in ``skip`` (its hash unchanged)."""
    if not skip:
        return plan
    return dataclasses.replace(plan, entries=tuple(e for e in plan.entries if e.method not in skip))


def skipped_note(run: Launch) -> str:
    """What a launch's summary line adds when it skips methods (``--skip-missing``,
    ``--only``)."""
    if not run.skip:
        return ""
    skipped = sum(e.method in run.skip for e in run.plan.entries)
    methods = ", ".join(m for m in run.spec.methods if m in run.skip)
    return f"; {methods} not run now ({plural(skipped, 'trial')}, left for a later launch)"


def start_estimate(
    plan: Plan, study: tuple[list[Any], dict[str, Any]] | None, threads: int
) -> InBackground:
    """Start estimating the trials of ``plan`` not done in ``study`` (``read_study``), at
    ``threads`` a trial (trials measured on another CPU or at other threads are not used)."""
    done, measured = finished(study[0] if study else [], plan.keys(), machine_at(threads))
    left = [e for e in plan.entries if e.key not in done]
    return InBackground(left, measured, CALIBRATION_SECONDS)


def print_estimate(run: Launch, not_now: set[str]) -> dict[str, TrialEstimate] | None:
    """Print what the trials this launch runs will cost (``sweeper.plan``'s estimate: from
    the study's finished trials, else a quick calibration) before they start, those of
    ``not_now`` (``--max-trials``) left out as ``--only``'s are; return the estimates, or
    None when they could not be made (the launch goes on without them)."""
    estimates = run.estimate.result()
    if isinstance(estimates, BaseException):  # a calibration that fails must not stop a study
        run.say(f"sweeper launch: no estimate: {type(estimates).__name__}: {estimates}")
        return None
    estimates = {key: e for key, e in estimates.items() if key not in not_now}
    entries = run.plan.entries
    done = {e.key for e in entries if e.key not in estimates}
    lines = summary_lines(entries, done, estimates, run.spec.execution, run.estimate.seconds)
    run.say("\n".join(f"estimate: {line}" for line in lines))
    return estimates
