"""The live progress display of ``sweeper launch``.

On a terminal: a small block redrawn in place every ``interval`` seconds (trials done per
method, the trials running with their env step, throughput and ETA), with events printed
above it. Elsewhere (CI logs, files): events and a summary line every ``log_interval``
seconds, as plain lines.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from typing import TextIO

from agent.config import Outcome
from sweeper.plan import TrialEstimate, format_duration, makespan
from sweeper.storage import KeyStatus

#: what a key can be during a launch: left or running, then how its trial ended
State = KeyStatus | Outcome
STATES: tuple[State, ...] = (
    KeyStatus.LEFT,
    KeyStatus.RUNNING,
    Outcome.COMPLETED,
    Outcome.DIVERGED,
    Outcome.PRUNED,
    Outcome.FAILED,
)
#: the states of a key whose trial is recorded with a result
DONE = (Outcome.COMPLETED, Outcome.DIVERGED, Outcome.PRUNED)
#: predicted seconds of work a launch must have done before its own pace corrects the
#: estimates (before that, a slow start-up would be taken for a slow machine)
MIN_PACED_WORK = 60.0


def format_count(n: float) -> str:
    """``12345`` -> ``"12.3k"``."""
    return f"{n / 1000:.1f}k" if n >= 1000 else f"{n:.0f}"


class LaunchProgress:
    """The progress of a launch: tracks the state and env step of every plan key and draws
    them on ``stream``."""

    def __init__(
        self,
        study: str,
        keys: list[str],
        env_steps: int,
        stream: TextIO | None = None,
        *,
        interval: float = 1.5,
        log_interval: float = 30.0,
        tty: bool | None = None,
        estimates: Mapping[str, TrialEstimate] | None = None,
        workers: int = 1,
    ) -> None:
        """``estimates`` (``sweeper.plan._estimate``): each key's predicted seconds, for an ETA
        that knows a trial's cheap seed phase from its training; without them the ETA is
        the env steps left over the launch's env steps per second. ``workers``: trials at
        once."""
        self.study = study
        self.env_steps = env_steps
        self.stream = sys.stderr if stream is None else stream
        self.tty = self.stream.isatty() if tty is None else tty
        self.interval = interval if self.tty else log_interval
        # the launch marks the keys it runs; the others were done before it
        self.states: dict[str, State] = dict.fromkeys(keys, Outcome.COMPLETED)
        self.steps: dict[str, int] = {}
        self.estimates, self.workers = estimates, workers
        # the work this launch did: env steps and their predicted seconds, and each running
        # key's step it has counted up to (a resumed trial starts at its checkpoint's)
        self._advanced, self._predicted = 0.0, 0.0
        self._at: dict[str, int] = {}
        # running keys whose start-up (envs, encoder, the step-0 evaluation) is not counted yet
        self._starting: set[str] = set()
        # (time, env steps done, predicted seconds done) when the clock started
        self._start: tuple[float, float, float] | None = None
        # A trial reports only at its evaluations, minutes apart for a long one: the pace
        # is the trial-seconds up to each key's last report over the predicted seconds
        # reported, and a running key's clock restarts at its report (``_since``). Starts
        # and reports are timed at the next eta() call.
        self._busy = 0.0
        self._since: dict[str, float] = {}
        self._reported: set[str] = set()
        self._last_draw = -float("inf")
        self._drawn_lines = 0

    def set_state(self, key: str, state: State, from_step: int = 0) -> None:
        """Move ``key`` to one of ``STATES``; ``from_step``: the env step a RUNNING key's
        trial starts from (its checkpoint's: the steps before it are not this launch's)."""
        if state not in STATES:
            raise ValueError(f"state must be one of {tuple(map(str, STATES))}, got {state!r}")
        self.states[key] = STATES[STATES.index(state)]
        if state == KeyStatus.RUNNING:
            self._at[key] = self.steps[key] = from_step
            self._starting.add(key)
            self._since.pop(key, None)
        elif state == Outcome.COMPLETED:
            self._advance(key, self.env_steps)
        elif state == KeyStatus.LEFT:
            self.steps.pop(key, None)

    def set_step(self, key: str, step: int) -> None:
        """The env step ``key`` last reported."""
        self.steps[key] = step
        self._advance(key, step)

    def _advance(self, key: str, step: int) -> None:
        """Count the work of ``key`` from the step counted last up to ``step``: a resumed
        trial first reports again what its checkpoint holds, which is not new work."""
        at = self._at.get(key, 0)
        if step <= at:
            return
        self._advanced += step - at
        estimate = (self.estimates or {}).get(key)
        if estimate is not None:
            self._predicted += estimate.until(step) - self._counted(key, estimate)
        self._starting.discard(key)
        self._at[key] = step
        self._reported.add(key)

    def _counted(self, key: str, estimate: TrialEstimate) -> float:
        """Predicted seconds of ``key``'s trial counted so far: up to its step counted last,
        less its start-up while that is still to be counted (the wall time to its first
        report includes it)."""
        counted = estimate.until(self._at.get(key, 0))
        return counted - estimate.until(0) if key in self._starting else counted

    def work(self) -> float:
        """Env steps done so far, over all keys (those done before this launch too)."""
        total = 0.0
        for key, state in self.states.items():
            if state == KeyStatus.RUNNING:
                total += self.steps.get(key, 0)
            elif state != KeyStatus.LEFT:
                total += self.env_steps
        return total

    def eta(self, now: float) -> tuple[float, float | None]:
        """(env steps/s of this launch since the clock started, seconds left or None if
        unknown).

        With estimates: the trials left handed to the workers (``makespan``), the running
        ones holding theirs less the time since their last report, scaled by how much
        slower (or faster) than predicted this launch ran up to its last report once that
        is ``MIN_PACED_WORK`` predicted seconds of work."""
        if self._start is None:
            self._start = (now, self._advanced, self._predicted)
        for key in self._reported:
            self._busy += now - self._since.get(key, now)
            self._since[key] = now
        self._reported.clear()
        elapsed, done = now - self._start[0], self._advanced - self._start[1]
        rate = done / elapsed if elapsed > 0 else 0.0
        if self.estimates is None:
            remaining = self.env_steps * len(self.states) - self.work()
            return rate, (remaining / rate if rate > 0 else None)
        predicted_done = self._predicted - self._start[2]
        paced = predicted_done >= MIN_PACED_WORK and self._busy > 0
        pace = self._busy / predicted_done if paced else 1.0
        busy, left = [], []
        for key, state in self.states.items():
            estimate = self.estimates.get(key)
            if estimate is None:
                continue
            if state == KeyStatus.RUNNING:
                rest = estimate.seconds - self._counted(key, estimate)
                since = self._since.setdefault(key, now)
                busy.append(max(0.0, rest * pace - (now - since)))
            elif state == KeyStatus.LEFT:
                left.append(estimate.seconds * pace)
        return rate, makespan(left, self.workers, busy[: self.workers])

    def lines(self, now: float) -> list[str]:
        """The display: a summary line, then one line per method."""
        counts = {state: 0 for state in STATES}
        methods: dict[str, list[int]] = {}
        for key, state in self.states.items():
            counts[state] += 1
            line = methods.setdefault(key.split("/")[0], [0, 0])
            line[0] += state in DONE
            line[1] += 1
        done = sum(counts[state] for state in DONE)
        rate, eta = self.eta(now)
        summary = f"{self.study}: {done}/{len(self.states)} trials done"
        if counts[Outcome.DIVERGED]:
            summary += f" ({counts[Outcome.DIVERGED]} diverged)"
        summary += f", {counts[KeyStatus.RUNNING]} running, {counts[Outcome.FAILED]} failed"
        summary += f" | {format_count(rate)} env steps/s"
        summary += f" | ETA {format_duration(eta) if eta is not None else '?'}"
        lines = [summary]
        width = max(len(m) for m in methods)
        for method, (method_done, total) in methods.items():
            running = [
                f"{key.split('/', 1)[1]} @ {format_count(self.steps.get(key, 0))}"
                for key, state in self.states.items()
                if state == KeyStatus.RUNNING and key.split("/")[0] == method
            ]
            text = f"  {method:<{width}}  {method_done}/{total} done"
            if running:
                text += "  running " + ", ".join(running)
            lines.append(text)
        return lines

    def refresh(self, force: bool = False) -> None:
        """Redraw if ``interval`` has passed (or ``force``)."""
        now = time.monotonic()
        if not force and now - self._last_draw < self.interval:
            self.eta(now)  # start the clock at the first call
            return
        self._last_draw = now
        lines = self.lines(now)
        if self.tty:
            self._clear()
            self.stream.write("\n".join(lines) + "\n")
            self._drawn_lines = len(lines)
        else:
            self.stream.write(lines[0] + "\n")
        self.stream.flush()

    def note(self, message: str) -> None:
        """Print an event (a trial finished, failed, ...) as its own line."""
        if self.tty:
            self._clear()
            self._drawn_lines = 0
            self._last_draw = -float("inf")  # redraw the block under it at once
        self.stream.write(message + "\n")
        self.stream.flush()

    def close(self) -> None:
        """Leave the last block on screen."""
        self._drawn_lines = 0

    def _clear(self) -> None:
        if self._drawn_lines:
            self.stream.write(f"\x1b[{self._drawn_lines}F\x1b[J")
