"""The live progress display of ``sweeper launch``.

On a terminal: a small block redrawn in place every ``interval`` seconds (trials done per
method, the trials running with their env step, throughput and ETA), with events printed
above it. Elsewhere (CI logs, files): events and a summary line every ``log_interval``
seconds, as plain lines.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from agent.config import Outcome
from sweeper.storage import KeyStatus

#: what a key can be during a launch: left or running, then how its trial ended
State = KeyStatus | Outcome
STATES: tuple[State, ...] = (
    KeyStatus.LEFT,
    KeyStatus.RUNNING,
    Outcome.COMPLETED,
    Outcome.DIVERGED,
    Outcome.FAILED,
)
#: the states of a key whose trial is recorded with a result
DONE = (Outcome.COMPLETED, Outcome.DIVERGED)


def format_seconds(seconds: float) -> str:
    """``3725`` -> ``"1:02:05"``."""
    seconds = max(0, round(seconds))
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"


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
    ) -> None:
        self.study = study
        self.env_steps = env_steps
        self.stream = sys.stderr if stream is None else stream
        self.tty = self.stream.isatty() if tty is None else tty
        self.interval = interval if self.tty else log_interval
        # the launch marks the keys it runs; the others were done before it
        self.states: dict[str, State] = dict.fromkeys(keys, Outcome.COMPLETED)
        self.steps: dict[str, int] = {}
        self._start: tuple[float, float] | None = None  # (time, work) when the launch began
        self._last_draw = -float("inf")
        self._drawn_lines = 0

    def set_state(self, key: str, state: State) -> None:
        """Move ``key`` to one of ``STATES``."""
        if state not in STATES:
            raise ValueError(f"state must be one of {tuple(map(str, STATES))}, got {state!r}")
        self.states[key] = STATES[STATES.index(state)]
        if state == KeyStatus.LEFT:
            self.steps.pop(key, None)

    def set_step(self, key: str, step: int) -> None:
        """The env step ``key`` last reported."""
        self.steps[key] = step

    def work(self) -> float:
        """Env steps done so far, over all keys."""
        total = 0.0
        for key, state in self.states.items():
            if state == KeyStatus.RUNNING:
                total += self.steps.get(key, 0)
            elif state != KeyStatus.LEFT:
                total += self.env_steps
        return total

    def eta(self, now: float) -> tuple[float, float | None]:
        """(env steps/s since the launch began, seconds left or None if unknown)."""
        work = self.work()
        if self._start is None:
            self._start = (now, work)
        elapsed, done = now - self._start[0], work - self._start[1]
        rate = done / elapsed if elapsed > 0 else 0.0
        remaining = self.env_steps * len(self.states) - work
        return rate, (remaining / rate if rate > 0 else None)

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
        summary += f" | ETA {format_seconds(eta) if eta is not None else '?'}"
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
