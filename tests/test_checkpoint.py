"""agent.checkpoint: a checkpoint that cannot be written is one clear OSError (issue 15).

No disk is filled: the file the checkpoint is streamed into, or the temporary file's
creation, is replaced by one that fails the way a full or read-only file system does.
"""

from __future__ import annotations

import errno
import io
import os
from pathlib import Path

import pytest
import torch
from conftest import tiny

import agent
from agent import checkpoint, storage_io


def snapshot(step: int = 50) -> checkpoint.Snapshot:
    return checkpoint.Snapshot(
        step=step,
        seconds=1.0,
        video_seconds=0.0,
        curve={"step": [0], "success_rate": [0.0]},
        agent={"w": torch.zeros(1000)},
        replay={"obs": torch.zeros(10, 3)},
        torch_rng=torch.get_rng_state(),
        cuda_rng=[],
        numpy_rng={"state": 1},
        env_rng={"state": 2},
    )


class FailingFile(io.FileIO):
    """An open file whose writes fail with ``code`` after the first kilobyte, as a disk
    that fills up mid-write does (torch then raises a RuntimeError of its own)."""

    code = errno.ENOSPC
    room = 1000

    def write(self, data: bytes) -> int:
        if self.tell() + len(data) > self.room:
            raise OSError(self.code, os.strerror(self.code))
        return super().write(data)


def fail_writes(monkeypatch: pytest.MonkeyPatch, code: int) -> None:
    FailingFile.code = code
    monkeypatch.setattr(storage_io.os, "fdopen", lambda fd, mode: FailingFile(fd, "wb"))


def test_round_trip(tmp_path: Path) -> None:
    config = tiny(checkpoint_dir=str(tmp_path), checkpoint_owner="study-a")
    checkpoint.save(str(tmp_path), config, snapshot())
    loaded = checkpoint.load(str(tmp_path), config)
    assert loaded is not None and loaded.step == 50 and loaded.curve == snapshot().curve
    assert torch.equal(loaded.agent["w"], torch.zeros(1000))
    assert [p.name for p in tmp_path.iterdir()] == [checkpoint.FILENAME]


def test_full_directory_is_one_clear_error_and_keeps_the_old_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = tiny(checkpoint_dir=str(tmp_path))
    checkpoint.save(str(tmp_path), config, snapshot(step=50))
    fail_writes(monkeypatch, errno.ENOSPC)
    with pytest.raises(OSError) as info:
        checkpoint.save(str(tmp_path), config, snapshot(step=100))
    assert str(info.value) == (
        f"checkpoint directory {tmp_path} is full (No space left on device): free space or "
        "set checkpoints: in the spec"
    )
    assert "inline_container" not in str(info.value)
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == [checkpoint.FILENAME]  # no partial file
    assert checkpoint.load(str(tmp_path), config).step == 50


@pytest.mark.parametrize(
    ("code", "problem"),
    [(errno.EACCES, "is not writable"), (errno.EROFS, "is read-only")],
)
def test_unwritable_directory_is_one_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, code: int, problem: str
) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(storage_io.tempfile, "mkstemp", refuse)
    with pytest.raises(OSError, match=f"checkpoint directory .* {problem} .*make it writable"):
        checkpoint.save(str(tmp_path), tiny(), snapshot())
    assert list(tmp_path.iterdir()) == []


def test_other_errors_are_not_disguised(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(obj: object, f: object) -> None:
        raise RuntimeError("a bug, not the disk")

    monkeypatch.setattr(checkpoint.torch, "save", broken)
    with pytest.raises(RuntimeError, match="a bug, not the disk"):
        checkpoint.save(str(tmp_path), tiny(), snapshot())
    assert list(tmp_path.iterdir()) == []


def test_trial_with_a_full_checkpoint_directory_fails_with_the_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = tiny(
        total_steps=100, seed_steps=100, checkpoint_every=50, checkpoint_dir=str(tmp_path)
    )
    fail_writes(monkeypatch, errno.ENOSPC)
    with pytest.raises(OSError, match=r"^checkpoint directory .* is full \(No space left"):
        agent.train(config)
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
