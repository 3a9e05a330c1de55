"""What a plan will cost before it is spent: each trial's wall time and the study's.

A trial's seconds come from the study's own finished trials of the same method when it
has some run on this CPU kind at the same threads (the mean of their recorded ``seconds``),
else from a calibration on this machine
(``agent.calibrate``: a few seconds of each part of a trial). The study's wall time is the
trials left, handed in the driver's run order to ``workers`` concurrent slots, each to the
first free one (the driver's own scheduling).
"""

from __future__ import annotations

import heapq
import os
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sweeper.plan._entries import PlanEntry, run_order
from sweeper.plan._halving import Schedule
from sweeper.spec import plural

if TYPE_CHECKING:
    from agent.calibrate import TrialCosts
    from agent.config import TrialConfig
    from sweeper.spec import Execution

#: above this much trial time on CPU, ``sweeper launch`` and ``sweeper plan`` warn
CPU_WARNING_SECONDS = 24 * 3600


def format_duration(seconds: float) -> str:
    """A duration as people read one: ``42 s``, ``12 min``, ``11 h 41 min``, ``2 d 3 h``."""
    seconds = max(0, round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    minutes = round(seconds / 60)
    if minutes < 60:
        return f"{minutes} min"
    hours, minutes = divmod(minutes, 60)
    if hours < 24:
        return f"{hours} h {minutes} min" if minutes else f"{hours} h"
    days, hours = divmod(round(seconds / 3600), 24)
    return f"{days} d {hours} h" if hours else f"{days} d"


def makespan(durations: Iterable[float], workers: int, busy: Sequence[float] = ()) -> float:
    """Wall time of ``durations`` run in order on ``workers`` slots, each to the slot that
    frees first; ``busy``: the seconds left of trials already running (they hold slots)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    free = sorted([*busy, *[0.0] * max(0, workers - len(busy))])
    heapq.heapify(free)
    end = max(free, default=0.0)
    for duration in durations:
        start = heapq.heappop(free)
        heapq.heappush(free, start + duration)
        end = max(end, start + duration)
    return end


def machine_at(threads: int) -> dict[str, str]:
    """The fields of a trial's machine record (``agent.machine.describe``) its seconds
    depend on most, for this machine at ``threads`` torch threads a trial: a study's trials
    measured elsewhere say little of a trial here (``sweeper.storage.finished``)."""
    from agent.machine import cpu_id  # loads torch: only once an estimate is made

    return {"cpu": cpu_id(), "threads": str(threads)}


def local_workers(max_concurrent: int, threads_per_trial: int, cores: int | None = None) -> int:
    """Trials that run at full speed at once on this machine: ``max_concurrent``, at most
    one per ``threads_per_trial`` cores (more share the cores and each runs slower)."""
    cores = (os.cpu_count() or 1) if cores is None else cores
    return max(1, min(max_concurrent, cores // threads_per_trial))


@dataclass(frozen=True)
class TrialEstimate:
    """One trial's predicted wall seconds, where the figure comes from, and (calibrated)
    the costs of its parts, which say how the seconds spread over its steps."""

    seconds: float
    source: str  # "calibrated" or "measured"
    config: TrialConfig
    costs: TrialCosts | None = None

    def until(self, step: int) -> float:
        """Predicted seconds from the trial's start to env step ``step``: by its parts'
        costs (random-action seed steps are cheap), else evenly over its policy steps. A
        measured trial's seconds are nearly all SAC updates: spread over every step, a 1/2
        trial's seed phase (1,000 steps in 50 s) made the ETA say 5 min for 1 h 35 min."""
        if self.costs is not None:
            return self.costs.seconds(self.config, step)
        total = self.config.total_steps
        seed = self.config.seed_steps if self.config.seed_steps < total else 0  # all seed: evenly
        return self.seconds * max(0, min(step, total) - seed) / (total - seed)


def estimate_trials(
    entries: Sequence[PlanEntry],
    measured: dict[str, float],
    seconds_per_part: float = 0.5,
    stop: threading.Event | None = None,
) -> dict[str, TrialEstimate]:
    """Each entry's ``TrialEstimate``: its method's ``measured`` mean where there is one,
    else calibrated on this machine, timing each part for ``seconds_per_part``; once
    ``stop`` is set the calibration raises ``agent.calibrate.Stopped``."""
    estimates = {}
    to_calibrate = [e for e in entries if e.method not in measured]
    for entry in entries:
        if entry.method in measured:
            estimates[entry.key] = TrialEstimate(
                measured[entry.method], "measured", entry.trial_config
            )
    if to_calibrate:
        from agent.calibrate import Calibration

        with Calibration(seconds=seconds_per_part, stop=stop) as calibration:
            for entry in to_calibrate:
                config = entry.trial_config
                costs = calibration.costs(config)
                estimates[entry.key] = TrialEstimate(
                    costs.seconds(config), "calibrated", config, costs
                )
    return estimates


class InBackground:
    """``estimate_trials`` in a thread, so the calibration runs while Ray and the workers
    start; ``result()`` waits for it: the estimates, or the exception it raised. ``stop()``
    ends it early and waits: call it before the process may exit (a launch that ends
    first), since a thread still in torch or MuJoCo at exit aborts the process."""

    THREAD_NAME = "sweeper-calibration"

    def __init__(
        self, entries: Sequence[PlanEntry], measured: dict[str, float], seconds_per_part: float
    ) -> None:
        self.seconds = 0.0
        self._result: dict[str, TrialEstimate] | BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run,
            args=(entries, measured, seconds_per_part),
            name=self.THREAD_NAME,
            daemon=True,
        )
        self._thread.start()

    def _run(
        self, entries: Sequence[PlanEntry], measured: dict[str, float], seconds: float
    ) -> None:
        start = time.perf_counter()
        try:
            self._result = estimate_trials(entries, measured, seconds, self._stop)
        except BaseException as e:  # handed to result(): the launch goes on without
            self._result = e
        self.seconds = time.perf_counter() - start

    def result(self) -> dict[str, TrialEstimate] | BaseException:
        self._thread.join()
        assert self._result is not None
        return self._result

    def stop(self) -> None:
        """End the calibration at its next timed call and wait for the thread."""
        self._stop.set()
        self._thread.join()


def summary_lines(
    entries: Sequence[PlanEntry],
    done: set[str],
    estimates: dict[str, TrialEstimate],
    execution: Execution,
    calibration_seconds: float | None = None,
) -> list[str]:
    """What the trials left will cost: trial time, wall time at the spec's ``execution``
    (concurrency, threads, GPUs) on this machine, how the figures were made (a calibration
    of ``calibration_seconds``), and the warning past a day of CPU."""
    threads_per_trial = execution.threads_per_trial
    left = [e for e in sorted(entries, key=run_order) if e.key not in done]
    trial_seconds = sum(estimates[e.key].seconds for e in left)
    workers = local_workers(execution.max_concurrent, threads_per_trial)
    wall = makespan([estimates[e.key].seconds for e in left], workers)
    lines = [
        f"left: {len(left)} of {plural(len(entries), 'trial')}, "
        f"{format_duration(trial_seconds)} of trial time; about {format_duration(wall)} at "
        f"{plural(workers, 'trial')} at once on this machine "
        f"({plural(os.cpu_count() or 1, 'core')}, {plural(threads_per_trial, 'thread')} a trial)"
    ]
    sources = {e.source for e in estimates.values()}
    if "calibrated" in sources and calibration_seconds is not None:
        load = os.getloadavg()[0]
        lines.append(
            f"calibrated in {format_duration(calibration_seconds)} here, at a load average "
            f"of {load:.1f}" + (": a busy machine gives slower figures" if load > 1 else "")
        )
    if execution.gpus_per_trial == 0 and trial_seconds > CPU_WARNING_SECONDS:
        lines.append(
            f"warning: this is {format_duration(trial_seconds)} of CPU trial time; on a "
            "cluster with GPUs set execution.gpus_per_trial (e.g. 0.25: four trials a GPU), "
            "see docs/cluster.md"
        )
    return lines


def halving_seconds(
    entries: Sequence[PlanEntry], estimates: dict[str, TrialEstimate], schedule: Schedule
) -> float:
    """Trial time of the plan under its successive halving: per method, ``sizes[r]``
    configurations x the seeds run from stop ``r - 1`` to stop ``r``, each segment at the
    mean predicted cost of the method's trials over it."""
    total = 0.0
    for method in sorted({e.method for e in entries}):
        mine = [estimates[e.key] for e in entries if e.method == method]
        seeds = len({e.seed for e in entries if e.method == method})
        previous = 0
        for stop, size in zip(schedule.stops, schedule.sizes, strict=True):
            segment = sum(e.until(stop) - e.until(previous) for e in mine) / len(mine)
            total += size * seeds * segment
            previous = stop
    return total
