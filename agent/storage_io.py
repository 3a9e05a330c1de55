"""Checkpoint bytes in a local directory or at an object-store URI.

A trial retried on another node must find its checkpoint, so the checkpoint location is
either a directory every node mounts (NFS, a Docker volume) or a URI that every node
reaches (``s3://bucket/prefix``, ``gs://...``, any fsspec URL). Local paths need nothing
extra; a URI scheme needs its fsspec backend installed (``pip install s3fs`` for ``s3://``).

Writes are atomic either way: a reader sees the old bytes or the new ones, never a torn
file. Locally that is a temporary file in the same directory, fsync, rename; an object
store commits an object only when its upload completes. (URIs of file systems with real
files, such as fsspec's ``local://`` or ``sftp://``, are written in place: not atomic.)
"""

from __future__ import annotations

import contextlib
import io
import os
import posixpath
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

_URI_RE = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


#: the file a trial's checkpoint is in, inside its ``checkpoint_dir`` (``agent.checkpoint``)
CHECKPOINT_FILE = "checkpoint.pt"


def is_uri(location: str) -> bool:
    """True for ``scheme://...`` locations other than ``file://``."""
    return bool(_URI_RE.match(location)) and not location.startswith("file://")


def _local(location: str) -> Path:
    return Path(location.removeprefix("file://"))


def _filesystem(uri: str) -> tuple[Any, str]:
    import fsspec  # only for URIs: local checkpoints need no extra package

    try:
        return fsspec.core.url_to_fs(uri)
    except (ImportError, ValueError) as e:
        raise ValueError(f"checkpoint location {uri!r}: {e}") from None


def join(location: str, *parts: str) -> str:
    """``location`` with ``parts`` appended, keeping a URI a URI (``Path`` would mangle ``//``)."""
    if is_uri(location):
        return "/".join([location.rstrip("/"), *(p.strip("/") for p in parts)])
    return str(_local(location).joinpath(*parts))


def open_read(location: str) -> BinaryIO | None:
    """The bytes at ``location`` as a binary file, or None if there is nothing there.

    A local file is opened, not read into memory (checkpoints can be gigabytes); a URI's
    object is downloaded.
    """
    if not is_uri(location):
        try:
            return _local(location).open("rb")
        except FileNotFoundError:
            return None
    fs, path = _filesystem(location)
    try:
        return io.BytesIO(fs.cat_file(path))
    except FileNotFoundError:
        return None


def write_atomic(location: str, write: Callable[[BinaryIO], object]) -> None:
    """Call ``write(file)`` and commit what it wrote at ``location`` atomically.

    Local files are streamed to disk (no copy in memory, for large checkpoints); a URI's
    bytes are collected in memory and uploaded in one piece.
    """
    if is_uri(location):
        buffer = io.BytesIO()
        write(buffer)
        fs, path = _filesystem(location)
        try:
            fs.pipe_file(path, buffer.getvalue())  # one upload: visible only once complete
        except FileNotFoundError:  # a file system with real directories (local://, sftp://)
            fs.makedirs(posixpath.dirname(path), exist_ok=True)
            fs.pipe_file(path, buffer.getvalue())
        return
    path = _local(location)
    for attempt in range(3):
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
            break
        except FileNotFoundError:  # an emptied parent removed meanwhile (``remove``): again
            if attempt == 2:
                raise
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    # fsync the directory too, so the rename itself survives a crash
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def exists(location: str) -> bool:
    """Whether there is a file or folder at ``location``."""
    if is_uri(location):
        fs, path = _filesystem(location)
        return bool(fs.exists(path))
    return _local(location).exists()


def remove(location: str, parents: int = 0) -> None:
    """Delete ``location`` and everything under it (a trial's checkpoint folder once its
    result is recorded), then up to ``parents`` folders above it that it leaves empty (a
    local path; an object store has no empty folders); nothing there is fine. A folder
    another writer fills meanwhile is kept, and ``write_atomic`` makes again a parent
    removed under it."""
    if is_uri(location):
        fs, path = _filesystem(location)
        with contextlib.suppress(FileNotFoundError):
            fs.rm(path, recursive=True)
        return
    folder = _local(location)
    with contextlib.suppress(FileNotFoundError):
        shutil.rmtree(folder)
    for parent in list(folder.parents)[:parents]:
        try:
            parent.rmdir()
        except FileNotFoundError:  # gone already
            continue
        except OSError:  # not empty: another trial's
            return
