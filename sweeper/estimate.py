"""What a plan will cost before it is spent: each trial's wall time and the study's.

A trial's seconds come from the study's own finished trials of the same method when it
has some (the mean of their recorded ``seconds``), else from a calibration on this machine
(``agent.calibrate``: a few seconds of each part of a trial). The study's wall time is the
trials left, handed in the driver's run order to ``workers`` concurrent slots, each to the
first free one (the driver's own scheduling).
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from sweeper.plan import PlanEntry

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


def local_workers(max_concurrent: int, threads_per_trial: int, cores: int | None = None) -> int:
    """Trials that run at full speed at once on this machine: ``max_concurrent``, at most
    one per ``threads_per_trial`` cores (more share the cores and each runs slower)."""
    cores = (os.cpu_count() or 1) if cores is None else cores
    return max(1, min(max_concurrent, cores // threads_per_trial))


@dataclass(frozen=True)
class TrialEstimate:
    """One trial's predicted wall seconds and where the figure comes from."""

    seconds: float
    source: str  # "calibrated" or "measured"


def measured_seconds(trials: Iterable[tuple[str, float]]) -> dict[str, float]:
    """Per method, the mean of its finished trials' recorded seconds (``(method, seconds)``
    pairs)."""
    by_method: dict[str, list[float]] = {}
    for method, seconds in trials:
        by_method.setdefault(method, []).append(seconds)
    return {m: sum(v) / len(v) for m, v in by_method.items()}


def estimate_trials(
    entries: Sequence[PlanEntry], measured: dict[str, float], calibrate: bool = True
) -> dict[str, TrialEstimate]:
    """Each entry's ``TrialEstimate``: its method's ``measured`` mean where there is one,
    else calibrated on this machine (``calibrate=False``: left out)."""
    estimates = {}
    to_calibrate = [e for e in entries if e.method not in measured]
    for entry in entries:
        if entry.method in measured:
            estimates[entry.key] = TrialEstimate(measured[entry.method], "measured")
    if to_calibrate and calibrate:
        from agent.calibrate import Calibration

        with Calibration() as calibration:
            for entry in to_calibrate:
                costs = calibration.costs(entry.trial_config)
                estimates[entry.key] = TrialEstimate(
                    costs.seconds(entry.trial_config), "calibrated"
                )
    return estimates
