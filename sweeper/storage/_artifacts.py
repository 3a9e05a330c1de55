"""Trial artifacts (episode videos) in an Optuna artifact store that the spec names.

The bytes live in a directory or at an object-store URI (``spec.artifacts``; by default
``artifacts/`` next to the SQLite database, or ``runs/<study>/artifacts``); the study
database holds each artifact's meta in the trial's system attrs, the way
``optuna.artifacts.upload_artifact`` writes it, so ``optuna.artifacts.get_all_artifact_meta``
and optuna-dashboard list it on the trial's page. Only the driver uploads: a worker's video
comes back to it as bytes, like the metrics.

``upload_once`` makes a retried trial store a video once: an artifact of the same file
name on the same trial is kept and the new bytes dropped. It writes the bytes first and the
meta second, so a failed upload leaves no meta pointing at nothing.
"""

from __future__ import annotations

import dataclasses
import io
import json
import mimetypes
import re
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

from agent import storage_io

if TYPE_CHECKING:
    import optuna

    from sweeper.spec import StudySpec

#: the trial system-attr prefix of Optuna's artifact meta (``optuna.artifacts``' own format)
ATTR_PREFIX = "artifacts:"
_ID_RE = re.compile(r"^[0-9a-fA-F-]+$")


def artifact_location(spec: StudySpec) -> str:
    """Where the study's artifacts live: ``spec.artifacts``, else ``artifacts/`` beside
    the SQLite database file, else ``runs/<study>/artifacts``."""
    from sweeper.storage._urls import sqlite_path

    if spec.artifacts is not None:
        return spec.artifacts
    database = sqlite_path(spec.storage_url)
    folder = database.parent if database is not None else spec.run_dir
    return str(folder / "artifacts")


class ArtifactStore:
    """Optuna's ``ArtifactStore`` protocol over ``agent.storage_io`` (the checkpoints'
    machinery): a local directory, or any fsspec URI every node and the dashboard reach.
    Writes are atomic: a reader never sees half a video."""

    def __init__(self, location: str) -> None:
        self.location = location

    def _where(self, artifact_id: str) -> str:
        if not _ID_RE.match(artifact_id):
            raise ValueError(f"invalid artifact id {artifact_id!r}")
        return storage_io.join(self.location, artifact_id)

    def open_reader(self, artifact_id: str) -> BinaryIO:
        from optuna.artifacts.exceptions import ArtifactNotFound

        source = storage_io.open_read(self._where(artifact_id))
        if source is None:
            raise ArtifactNotFound(f"no artifact {artifact_id} in {self.location}")
        return source

    def write(self, artifact_id: str, content_body: BinaryIO) -> None:
        data = content_body.read()
        storage_io.write_atomic(self._where(artifact_id), lambda f: f.write(data))

    def remove(self, artifact_id: str) -> None:
        where = self._where(artifact_id)
        if storage_io.is_uri(where):
            storage_io.remove(where)
        else:
            Path(where.removeprefix("file://")).unlink(missing_ok=True)


def trial_artifacts(storage: optuna.storages.BaseStorage, trial_id: int) -> list[dict[str, Any]]:
    """The artifact meta of a trial (``artifact_id``, ``filename``, ``mimetype``,
    ``encoding``), in no particular order."""
    return artifacts_in(storage.get_trial_system_attrs(trial_id))


def artifacts_in(system_attrs: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The artifact meta among a trial's system attrs (a ``FrozenTrial``'s, or read)."""
    return [json.loads(v) for k, v in system_attrs.items() if k.startswith(ATTR_PREFIX)]


def upload_once(
    storage: optuna.storages.BaseStorage,
    trial_id: int,
    filename: str,
    data: bytes,
    store: ArtifactStore,
) -> str | None:
    """Store ``data`` as the trial's artifact ``filename``; return its id, or None when the
    trial already has an artifact of that name (a retried trial's second recording)."""
    from optuna.artifacts import ArtifactMeta

    if any(meta["filename"] == filename for meta in trial_artifacts(storage, trial_id)):
        return None
    mimetype, encoding = mimetypes.guess_type(filename)
    meta = ArtifactMeta(
        artifact_id=str(uuid.uuid4()),
        filename=filename,
        mimetype=mimetype or "application/octet-stream",
        encoding=encoding,
    )
    store.write(meta.artifact_id, io.BytesIO(data))
    storage.set_trial_system_attr(
        trial_id, ATTR_PREFIX + meta.artifact_id, json.dumps(dataclasses.asdict(meta))
    )
    return meta.artifact_id
