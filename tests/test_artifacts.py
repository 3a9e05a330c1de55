"""Episode videos as Optuna artifacts: the spec's choice, the store, one upload per trial,
the CI study's videos served by optuna-dashboard, and a worker killed after recording."""

from __future__ import annotations

import io
import json
import os
import signal
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import optuna
import pytest
import ray
import yaml
from conftest import CI_SPEC, running_dashboard
from optuna.artifacts import get_all_artifact_meta
from optuna.trial import TrialState

from agent import video
from agent.config import TrialResult
from agent.metrics import normalized_auc
from sweeper.run._launch import launch, prepare
from sweeper.spec._models import SpecError, load_spec, parse_spec
from sweeper.storage import open_storage, trial_attr
from sweeper.storage._artifacts import ArtifactStore, artifact_location, upload_once

OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # this machine only
optuna.logging.set_verbosity(optuna.logging.WARNING)
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake train below


def ci_data(**changes) -> dict:
    data = yaml.safe_load(CI_SPEC.read_text())
    data.update(changes)
    return data


# ---- the spec ------------------------------------------------------------------------------
def test_videos_default_to_the_last_evaluation_and_can_be_chosen_or_off() -> None:
    spec = parse_spec(ci_data())
    assert spec.video_steps == (300,)
    assert all(e.trial_config.video_steps == (300,) for e in _plan(spec).entries)
    assert parse_spec(ci_data(videos="none")).video_steps == ()
    assert parse_spec(ci_data(videos=[300, 0, 100])).video_steps == (0, 100, 300)
    with pytest.raises(SpecError, match=r"videos: 150 is not an evaluation step"):
        parse_spec(ci_data(videos=[100, 150]))
    with pytest.raises(SpecError, match="videos: must be 'last', 'none' or a list"):
        parse_spec(ci_data(videos="first"))


def test_video_steps_leave_the_plan_hash_alone() -> None:
    """Filming changes no curve: a study launched before videos existed still resumes."""
    on, off = parse_spec(ci_data()), parse_spec(ci_data(videos="none"))
    assert _plan(on).hash == _plan(off).hash


def _plan(spec):
    from sweeper.plan._entries import build_plan

    return build_plan(spec)


def test_artifacts_live_beside_the_sqlite_database_by_default(tmp_path) -> None:
    local = parse_spec(ci_data(storage=f"sqlite:///{tmp_path / 'db' / 'study.db'}"))
    assert artifact_location(local) == str(tmp_path / "db" / "artifacts")
    assert artifact_location(parse_spec(ci_data())) == str(Path("runs/ci/artifacts"))
    server = parse_spec(ci_data(storage="postgresql://u@host/db"))
    assert artifact_location(server) == str(Path("runs/ci/artifacts"))
    uri = parse_spec(ci_data(storage="postgresql://u@host/db", artifacts="s3://bucket/videos"))
    assert artifact_location(uri) == "s3://bucket/videos"


# ---- the store and the upload ---------------------------------------------------------------
@pytest.mark.parametrize("where", ["local", "memory://"])
def test_upload_once_stores_a_file_once_per_trial_and_optuna_lists_it(tmp_path, where) -> None:
    location = str(tmp_path / "artifacts") if where == "local" else f"memory://{tmp_path.name}"
    store = ArtifactStore(location)
    study = optuna.create_study(storage=optuna.storages.InMemoryStorage())
    first, second = study.ask(), study.ask()
    storage = study._storage
    artifact_id = upload_once(storage, first._trial_id, "episode-step300.mp4", b"one", store)
    assert upload_once(storage, first._trial_id, "episode-step300.mp4", b"two", store) is None
    assert upload_once(storage, second._trial_id, "episode-step300.mp4", b"3", store) is not None
    (meta,) = get_all_artifact_meta(first)
    assert (meta.artifact_id, meta.filename, meta.mimetype) == (
        artifact_id,
        "episode-step300.mp4",
        "video/mp4",
    )
    with store.open_reader(artifact_id) as f:
        assert f.read() == b"one"  # the retry's bytes were dropped
    store.remove(artifact_id)
    with pytest.raises(optuna.artifacts.exceptions.ArtifactNotFound):
        store.open_reader(artifact_id)
    with pytest.raises(ValueError, match="invalid artifact id"):
        store.open_reader("../study.db")


# ---- the CI study, end to end ---------------------------------------------------------------
def get(url: str) -> bytes:
    with OPENER.open(url, timeout=30) as response:
        return response.read()


def test_ci_study_stores_one_video_per_trial_and_the_dashboard_serves_it(ci_study) -> None:
    """studies/ci.yaml as launched: each trial's final evaluation episode is one artifact in
    artifacts/ beside the database; `sweeper dashboard` lists it on the trial and serves a
    video of the episode's 51 frames (reset + 50 steps)."""
    stored = optuna.load_study(study_name="ci", storage=ci_study.storage_url).get_trials()
    storage = open_storage(ci_study.storage_url, create=False)
    for trial in stored:
        (meta,) = get_all_artifact_meta(trial, storage=storage)
        assert meta.filename == f"episode-step300.{video.default_format()}"
        assert trial_attr(trial, "videos") == {meta.filename: meta.artifact_id}
        assert 0 < trial.user_attrs["video_seconds"] < trial.user_attrs["seconds"]
        assert (ci_study.workdir / "artifacts" / meta.artifact_id).is_file()
    storage.engine.dispose()

    with running_dashboard(ci_study) as page:
        base, study_id = page.split("/dashboard/")[0], int(page.rsplit("/", 1)[1])
        detail = json.loads(get(f"{base}/api/studies/{study_id}"))
        videos = {}
        for served in detail["trials"]:
            (artifact,) = served["artifacts"]
            assert artifact["mimetype"].startswith(("video/", "image/"))
            url = f"{base}/artifacts/{study_id}/{served['trial_id']}/{artifact['artifact_id']}"
            videos[served["number"]] = get(url)
    assert sorted(videos) == sorted(t.number for t in stored) and len(videos) == 2
    for data in videos.values():
        assert len(data) < 300_000
        frames = video.decode_video(data, video.default_format())
        # 32-pixel images scaled to 128, side by side with a 4-pixel gap, a caption band
        assert frames.shape == (51, 160, 272, 3)
        assert frames[:, :128, :128].std() > 0  # the observation is drawn


# ---- a worker killed after recording --------------------------------------------------------
def attempt_video(attempt: int) -> bytes:
    """The GIF a trial's ``attempt`` (1 or 2) records: frames of another shade each time."""
    frame = np.full((32, 32, 3), 40 * attempt, np.uint8)
    frames = video.episode_frames([frame] * 3, frame, [f"attempt {attempt}"] * 3)
    return video.encode_video(frames, "gif")


def film_then_die(config, report=None, record=None):
    """Records its video, waits until the driver has stored it, and dies the first time;
    records it again (other bytes) and finishes the second time (as a resumed trial re-runs
    its last evaluation)."""
    root = Path(config.checkpoint_dir).parents[3]  # <checkpoints>/<study>/<method>/<id>/<seed>
    marker = Path(config.checkpoint_dir) / "died"
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    first = not marker.exists()
    record("episode-step300.gif", attempt_video(1 if first else 2))
    if first:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text("")
        deadline = time.monotonic() + 120
        while not any((root.parent / "artifacts").glob("*")):
            if time.monotonic() > deadline:  # the trial fails: the test sees no second attempt
                raise RuntimeError("the first attempt's video was never stored")
            time.sleep(0.1)
        os.kill(os.getpid(), signal.SIGKILL)
    steps = (0, 100, 200, 300)
    success = (0.0, 1.0, 1.0, 1.0)
    return TrialResult(
        steps=steps,
        metrics={"success_rate": success, "final_distance": (1.0, 0.0, 0.0, 0.0)},
        auc=normalized_auc(steps, success),
    )


@pytest.mark.slow
def test_a_worker_killed_after_recording_does_not_store_its_video_twice(tmp_path) -> None:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    data = ci_data(study="killed", methods={"pixel": {}}, storage=url)
    data["checkpoints"] = str(tmp_path / "checkpoints")
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(data))
    spec, plan = prepare(str(tmp_path / "spec.yaml"))
    assert launch(spec, plan, train=film_then_die, stream=io.StringIO()) == 0
    (trial,) = optuna.load_study(study_name="killed", storage=url).get_trials()
    assert trial.state == TrialState.COMPLETE
    assert trial.user_attrs["attempts"] == 2 and len(trial_attr(trial, "worker_deaths")) == 1
    storage = open_storage(url, create=False)
    (meta,) = get_all_artifact_meta(trial, storage=storage)
    storage.engine.dispose()
    assert trial_attr(trial, "videos") == {"episode-step300.gif": meta.artifact_id}
    assert [p.name for p in (tmp_path / "artifacts").iterdir()] == [meta.artifact_id]
    stored = (tmp_path / "artifacts" / meta.artifact_id).read_bytes()
    assert stored == attempt_video(1) != attempt_video(2)  # the first attempt's, kept
    assert load_spec(tmp_path / "spec.yaml").video_steps == (300,)


# ---- the report's pictures ------------------------------------------------------------------
def test_report_shows_final_frames_of_each_method_and_the_env_view(ci_study, ci_aggregate):
    from PIL import Image

    report = (ci_aggregate / "report.md").read_text()
    assert "## What the agents do" in report and "](final_frames.png)" in report
    for method in ("pixel", "linear"):  # one trial each: best and median are the same
        line = [x for x in report.splitlines() if x.startswith(f"| {method} |")][-1]
        assert "best: trial" in line and "median: trial" in line and "step 300" in line
    strip = np.asarray(Image.open(ci_aggregate / "final_frames.png").convert("RGB"))
    # two rows (methods) of two labelled 160x272 frames (best, median), 6 pixels apart
    assert strip.shape == (2 * (16 + 160) + 6, 2 * 272 + 6, 3)
    assert "## What the encoders see" in report and "](env_views.png)" in report
    views = np.asarray(Image.open(ci_aggregate / "env_views.png").convert("RGB"))
    # 4 resets in a 2 x 2 grid, each view | goal scaled from 32 to 128 pixels
    assert views.shape == (2 * (16 + 128) + 6, 2 * (2 * 128 + 6) + 6, 3)
