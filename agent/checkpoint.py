"""The trial checkpoint: what is saved, how it is written, loaded and checked.

A checkpoint is one file, ``checkpoint.pt`` in the trial's ``checkpoint_dir`` (a local
directory or an object-store URI, ``agent.storage_io``), holding a ``Snapshot`` of the
training loop plus three checks: the format number, the trial config (without the
``RUNTIME_FIELDS``) and the owner (``TrialConfig.checkpoint_owner``, the sweeper's study
uid). A SHA-256 digest of the contents is stored with them: a truncated or corrupt file
is a ``CorruptCheckpoint`` (the trial then starts again from step 0 and says so), while an
intact checkpoint of another config or owner is an error, since resuming it would mix two
trials.

``save(directory, config, snapshot)`` and ``load(directory, config)`` are the whole
interface. A write that fails for want of space or permission is raised as one OSError
naming the directory and the cause; the old checkpoint, if any, stays as it was.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
from typing import Any

import numpy as np
import torch

from agent import storage_io
from agent.config import TrialConfig, curve_fields

FILENAME = storage_io.CHECKPOINT_FILE
FORMAT = 1
#: a failed write's errno -> what is wrong with the directory, what to do about it
_WRITE_PROBLEMS = {
    errno.ENOSPC: ("is full", "free space"),
    errno.EDQUOT: ("is over its quota", "free space"),
    errno.EACCES: ("is not writable", "make it writable"),
    errno.EPERM: ("is not writable", "make it writable"),
    errno.EROFS: ("is read-only", "make it writable"),
}


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """The training loop at an episode end: enough to continue it exactly.

    ``curve`` is the evaluation curve so far (``{"step": [...], metric: [...]}``);
    ``agent`` and ``replay`` are the SAC and replay ``state_dict()``s; the random states
    are torch's (and CUDA's, an empty list on CPU), the trial's numpy generator's and the
    training env's generator's (``bit_generator.state``); ``machines`` the runs so far
    (``TrialResult.machines``).
    """

    step: int
    seconds: float
    video_seconds: float
    curve: dict[str, list[float]]
    agent: dict[str, Any]
    replay: dict[str, Any]
    torch_rng: torch.Tensor
    cuda_rng: list[torch.Tensor]
    numpy_rng: dict[str, Any]
    env_rng: dict[str, Any]
    machines: list[dict[str, Any]] = dataclasses.field(default_factory=list)


def save(directory: str, config: TrialConfig, snapshot: Snapshot) -> None:
    """Write ``snapshot`` of the trial ``config`` into ``directory``, atomically.

    Raises an OSError naming ``directory`` when it is full, read-only or not writable
    (torch reports such a failure as a RuntimeError, which is translated too).
    """
    state = {"format": FORMAT, "config": _config_key(config), "owner": config.checkpoint_owner}
    # not dataclasses.asdict: it would deep-copy the replay buffer
    state.update({f.name: getattr(snapshot, f.name) for f in dataclasses.fields(snapshot)})
    state = _to_tensors(state)
    state["digest"] = _digest(state)
    try:
        storage_io.write_atomic(_location(directory), lambda f: torch.save(state, f))
    except (OSError, RuntimeError) as exc:
        error = _write_error(directory, exc)
        if error is None:
            raise
        raise error from exc


class CorruptCheckpoint(Exception):
    """A checkpoint file that is truncated or corrupt: it cannot be resumed, only replaced."""


def load(directory: str, config: TrialConfig) -> Snapshot | None:
    """The checkpoint in ``directory``, or None if there is none. A truncated or corrupt
    file raises ``CorruptCheckpoint`` (one line naming the file); a checkpoint of another
    trial config, or of another owner (``config.checkpoint_owner``, e.g. another study with
    the same spec), is a ValueError."""
    location = _location(directory)
    source = storage_io.open_read(location)
    if source is None:
        return None
    try:
        with source:
            state = torch.load(source, map_location="cpu", weights_only=True)
        digest = state.pop("digest")
        if state.get("format") != FORMAT or digest != _digest(state):
            raise ValueError("digest or format mismatch")
    except Exception as exc:
        reason = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise CorruptCheckpoint(f"corrupt checkpoint {location}: {reason}") from None
    if state.get("owner") != config.checkpoint_owner:
        raise ValueError(
            f"checkpoint_dir {directory!r} holds a checkpoint of another study "
            f"(owner {state.get('owner')!r}, this trial's is {config.checkpoint_owner!r}); "
            "give each study its own checkpoint_dir"
        )
    if state["config"] != _config_key(config):
        raise ValueError(
            f"checkpoint_dir {directory!r} holds a checkpoint of another trial "
            "config; give each trial its own checkpoint_dir"
        )
    return Snapshot(
        step=int(state["step"]),
        seconds=float(state["seconds"]),
        video_seconds=float(state.get("video_seconds", 0.0)),  # absent before videos
        curve=state["curve"],
        agent=state["agent"],
        replay=state["replay"],
        torch_rng=state["torch_rng"],
        cuda_rng=state["cuda_rng"],
        numpy_rng=state["numpy_rng"],
        env_rng=state["env_rng"],
        machines=list(state.get("machines", [])),  # absent before machines were recorded
    )


def saved_step(directory: str) -> int | None:
    """The env step of the checkpoint in ``directory``, read without checking the file (so
    cheaply: a local file is memory-mapped and only its step is read); None when there is
    none or it cannot be read."""
    location = _location(directory)
    try:
        if storage_io.is_uri(location):
            source = storage_io.open_read(location)
            if source is None:
                return None
            with source:
                return int(torch.load(source, map_location="cpu", weights_only=True)["step"])
        state = torch.load(location, map_location="cpu", weights_only=True, mmap=True)
        return int(state["step"])
    except Exception:  # missing, truncated, unreadable: no step to resume from
        return None


def _location(directory: str) -> str:
    return storage_io.join(directory, FILENAME)


def _config_key(config: TrialConfig) -> str:
    """The trial config without the fields that do not change the curve."""
    return repr(curve_fields(config))


def _write_error(directory: str, exc: BaseException) -> OSError | None:
    """One clear OSError for a checkpoint write that failed in the file system, or None
    when ``exc`` is not such a failure.

    torch writes through the open file and turns the OSError it gets into a RuntimeError
    ("enforce fail at inline_container.cc"), with the OSError as its context.
    """
    chain, cause = [], exc
    while cause is not None and len(chain) < 10:
        chain.append(cause)
        cause = cause.__cause__ or cause.__context__
    os_error = next((e for e in chain if isinstance(e, OSError)), None)
    if os_error is None and "inline_container" not in str(exc):
        return None  # a bug elsewhere (a value torch cannot save, ...): raised as it is
    code = os_error.errno if os_error is not None else None
    reason = (os_error.strerror or str(os_error)) if os_error is not None else str(exc)
    problem, remedy = _WRITE_PROBLEMS.get(code, ("cannot be written", "check it"))
    return OSError(
        f"checkpoint directory {directory} {problem} ({reason}): {remedy} or set "
        "checkpoints: in the spec"
    )


def _digest(obj: Any) -> str:
    """SHA-256 over every value in a nested checkpoint (tensors by their bytes)."""
    h = hashlib.sha256()

    def visit(x: Any) -> None:
        if isinstance(x, torch.Tensor):
            x = x.detach().cpu().contiguous()
            h.update(f"T{x.dtype}{tuple(x.shape)}".encode())
            h.update(x.reshape(-1).view(torch.uint8).numpy())
        elif isinstance(x, dict):
            h.update(f"D{len(x)}".encode())
            for k in sorted(x, key=repr):
                h.update(repr(k).encode())
                visit(x[k])
        elif isinstance(x, list | tuple):
            h.update(f"L{len(x)}".encode())
            for v in x:
                visit(v)
        else:
            h.update(repr(x).encode())

    visit(obj)
    return h.hexdigest()


def _to_tensors(obj: Any) -> Any:
    """numpy arrays -> tensors (no copy), so the file loads with ``weights_only=True``."""
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj)
    if isinstance(obj, dict):
        return {k: _to_tensors(v) for k, v in obj.items()}
    return obj
