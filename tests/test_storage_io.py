"""agent.storage_io: checkpoint bytes at a local path or an object-store URI (fsspec)."""

from __future__ import annotations

import uuid

import pytest

from agent.storage_io import is_uri, join, open_read, write_atomic


def read_bytes(location: str) -> bytes | None:
    source = open_read(location)
    if source is None:
        return None
    with source:
        return source.read()


def write_bytes_atomic(location: str, data: bytes) -> None:
    write_atomic(location, lambda f: f.write(data))


def test_local_round_trip_overwrite_and_no_leftovers(tmp_path):
    target = join(str(tmp_path), "a", "b", "checkpoint.pt")
    assert read_bytes(target) is None
    write_bytes_atomic(target, b"first")
    write_bytes_atomic(target, b"second")
    assert read_bytes(target) == b"second"
    assert [p.name for p in (tmp_path / "a" / "b").iterdir()] == ["checkpoint.pt"]
    assert read_bytes(f"file://{target}") == b"second"


def test_failed_write_keeps_the_old_bytes(tmp_path):
    target = str(tmp_path / "checkpoint.pt")
    write_bytes_atomic(target, b"good")
    with pytest.raises(TypeError):
        write_bytes_atomic(target, "not bytes")  # type: ignore[arg-type]
    assert read_bytes(target) == b"good"
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]


def test_uri_round_trip_in_fsspec_memory_store():
    root = f"memory://bucket-{uuid.uuid4().hex[:8]}/study"
    target = join(root, "pixel/0/0", "checkpoint.pt")
    assert target == f"{root}/pixel/0/0/checkpoint.pt"
    assert read_bytes(target) is None
    write_bytes_atomic(target, b"\x00\x01state")
    write_bytes_atomic(target, b"\x00\x02state")
    assert read_bytes(target) == b"\x00\x02state"


def test_uri_of_a_file_system_with_directories_creates_them(tmp_path):
    target = f"local://{tmp_path}/new/dirs/checkpoint.pt"  # fsspec's local file system
    write_bytes_atomic(target, b"state")
    assert (tmp_path / "new" / "dirs" / "checkpoint.pt").read_bytes() == b"state"
    assert read_bytes(target) == b"state"


def test_uri_detection_and_join():
    assert is_uri("s3://bucket/x") and is_uri("gs://b") and is_uri("memory://x")
    assert not is_uri("/data/checkpoints") and not is_uri("runs/x")
    assert not is_uri("file:///data/checkpoints")
    assert join("s3://bucket/prefix/", "/pixel/", "checkpoint.pt") == (
        "s3://bucket/prefix/pixel/checkpoint.pt"
    )
    assert join("runs/x", "pixel", "checkpoint.pt") == "runs/x/pixel/checkpoint.pt"


def test_unknown_scheme_is_a_clear_error():
    with pytest.raises(ValueError, match=r"nosuchscheme://bucket/checkpoint\.pt"):
        write_bytes_atomic("nosuchscheme://bucket/checkpoint.pt", b"x")


def test_exists_on_a_path_and_a_uri(tmp_path):
    from agent.storage_io import exists

    assert not exists(str(tmp_path / "none")) and not exists(f"local://{tmp_path}/none")
    (tmp_path / "there").write_bytes(b"x")
    assert exists(str(tmp_path / "there")) and exists(f"local://{tmp_path}/there")
