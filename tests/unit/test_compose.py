"""The container setup (issue 14): `docker-compose.yml`, `Dockerfile` and `.dockerignore`.

`docker-compose config` validates the compose file and prints it resolved (anchors merged,
variables interpolated); the tests read that output, so they check what Compose itself makes of
the file. No Docker engine is needed. The `docker-compose` command is a system package the CI
installs (`.ci/system-deps.sh`): without it these tests fail, they do not skip.

The output's forms differ between Compose v1 (Debian 12's `docker-compose` 1.29) and v2 (short or
long volume and port syntax, command as a list or a string): the helpers below accept both.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
COMPOSE_FILE = REPO / "docker-compose.yml"
DOCKERFILE = REPO / "Dockerfile"
DOCKERIGNORE = REPO / ".dockerignore"
APP_SERVICES = ("migrate", "api", "worker")
SHARED_ENV = (
    "CITYTHERM_DATABASE_URL",
    "CITYTHERM_REDIS_URL",
    "CITYTHERM_STORAGE_DIR",
    "CITYTHERM_DATABASE_SRID",
)


def compose_config(tmp_path: Path, **env: str) -> dict[str, Any]:
    """`docker-compose config` of the repository's compose file, parsed. Runs with the variables
    the file reads removed from the environment (then `env` set) and an empty `--env-file`, so
    neither the caller's environment nor a developer's `.env` changes the result."""
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.fail(
            "docker-compose is not installed: `apt-get install -y docker-compose` "
            "(.ci/system-deps.sh installs it)"
        )
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("CITYTHERM_", "POSTGRES_", "COMPOSE_"))}
    clean.update(env)
    env_file = tmp_path / "empty.env"
    env_file.write_text("")
    proc = subprocess.run(
        [exe, "--env-file", str(env_file), "-f", str(COMPOSE_FILE), "config"],
        capture_output=True,
        text=True,
        env=clean,
        cwd=tmp_path,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, f"docker-compose config failed ({proc.returncode}):\n{proc.stderr}"
    cfg = yaml.safe_load(proc.stdout)
    assert isinstance(cfg, dict) and isinstance(cfg.get("services"), dict), proc.stdout
    return cfg


@pytest.fixture(scope="module")
def config(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return compose_config(tmp_path_factory.mktemp("compose"))


def _command(service: dict[str, Any]) -> list[str]:
    cmd = service.get("command", [])
    return shlex.split(cmd) if isinstance(cmd, str) else [str(c) for c in cmd]


def _mounts(service: dict[str, Any]) -> dict[str, str]:
    """target path -> source (volume name or host path) of a service's volumes, either syntax."""
    out = {}
    for v in service.get("volumes", []):
        if isinstance(v, str):
            source, target = v.split(":")[:2]
        else:
            source, target = v.get("source", ""), v["target"]
        out[target] = source
    return out


def _depends(service: dict[str, Any]) -> dict[str, str]:
    """dependency -> condition (`service_started` for the list form)."""
    dep = service.get("depends_on", {})
    if isinstance(dep, list):
        return dict.fromkeys(dep, "service_started")
    return {name: (d or {}).get("condition", "service_started") for name, d in dep.items()}


def _env(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):
        env = dict(e.split("=", 1) for e in env)
    return {k: str(v) for k, v in env.items()}


def test_services_exist(config: dict[str, Any]) -> None:
    assert set(config["services"]) >= {"db", "redis", "migrate", "api", "worker", "sweeper"}
    # exactly one sweeper (beat) runs: the scaled workers do not, the sweeper service does
    assert "--beat" not in config["services"]["worker"]["command"]
    assert "--beat" in config["services"]["sweeper"]["command"]


def test_db_and_redis_have_healthchecks_and_db_a_named_volume(config: dict[str, Any]) -> None:
    s = config["services"]
    assert s["db"]["image"].startswith("postgis/postgis:")
    assert "pg_isready" in " ".join(s["db"]["healthcheck"]["test"])
    assert "redis-cli" in s["redis"]["healthcheck"]["test"]
    data = _mounts(s["db"])["/var/lib/postgresql/data"]
    assert data in config.get("volumes", {}), "the database keeps its data in a named volume"
    # neither publishes a port: only the API is reachable from outside
    assert not s["db"].get("ports") and not s["redis"].get("ports")


def test_migrate_runs_db_upgrade_once_after_the_database_is_healthy(config: dict[str, Any]) -> None:
    m = config["services"]["migrate"]
    assert _command(m)[:2] == ["db", "upgrade"]
    assert _depends(m).get("db") == "service_healthy"
    assert str(m.get("restart", "no")) == "no"


@pytest.mark.parametrize("name", ["api", "worker"])
def test_api_and_worker_wait_for_migrate_and_redis(config: dict[str, Any], name: str) -> None:
    dep = _depends(config["services"][name])
    assert dep.get("migrate") == "service_completed_successfully"
    assert dep.get("redis") == "service_healthy"


def test_api_serves_on_8000_with_a_healthcheck(config: dict[str, Any]) -> None:
    api = config["services"]["api"]
    cmd = _command(api)
    assert cmd[0] == "serve" and "0.0.0.0" in cmd
    targets = [str(p["target"]) if isinstance(p, dict) else str(p).split(":")[-1] for p in api["ports"]]
    assert "8000" in targets
    check = " ".join(api["healthcheck"]["test"])
    assert "localhost:8000/conformance" in check and "curl" not in check


def test_worker_scales(config: dict[str, Any]) -> None:
    """`docker compose up --scale worker=N` needs a worker without a fixed name or host port."""
    w = config["services"]["worker"]
    assert _command(w)[0] == "worker"
    assert "container_name" not in w
    assert not w.get("ports")


def test_api_and_worker_share_storage_and_settings(config: dict[str, Any]) -> None:
    s = config["services"]
    api, worker = _mounts(s["api"]), _mounts(s["worker"])
    assert api.get("/data") == worker.get("/data") == "storage"
    assert "storage" in config.get("volumes", {}), "the storage is a named volume"
    envs = {name: _env(s[name]) for name in APP_SERVICES}
    for key in SHARED_ENV:
        values = {envs[name].get(key) for name in APP_SERVICES}
        assert len(values) == 1 and None not in values, f"{key} differs between {APP_SERVICES}: {values}"
    e = envs["api"]
    assert e["CITYTHERM_STORAGE_DIR"] == "/data"
    assert e["CITYTHERM_DATABASE_URL"].startswith("postgresql+psycopg://postgres:")
    assert e["CITYTHERM_DATABASE_URL"].endswith("@db:5432/citytherm")
    assert e["CITYTHERM_REDIS_URL"].startswith("redis://redis:6379/")
    assert e["CITYTHERM_DATABASE_SRID"] == "25832"  # the default


def test_password_and_srid_come_from_the_environment(tmp_path: Path) -> None:
    cfg = compose_config(tmp_path, POSTGRES_PASSWORD="s3cret", CITYTHERM_DATABASE_SRID="25833")
    s = cfg["services"]
    assert _env(s["db"])["POSTGRES_PASSWORD"] == "s3cret"
    for name in APP_SERVICES:
        e = _env(s[name])
        assert e["CITYTHERM_DATABASE_URL"] == "postgresql+psycopg://postgres:s3cret@db:5432/citytherm"
        assert e["CITYTHERM_DATABASE_SRID"] == "25833"


def test_app_services_run_the_image_built_from_the_dockerfile(config: dict[str, Any]) -> None:
    s = config["services"]
    images = {s[name]["image"] for name in APP_SERVICES}
    assert len(images) == 1
    for name in APP_SERVICES:
        build = s[name]["build"]
        context = build if isinstance(build, str) else build["context"]
        assert Path(context).resolve() == REPO


def dockerfile_instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile: comments dropped, continuation lines joined."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        line, pending = pending + line, ""
        word, _, args = line.partition(" ")
        out.append((word.upper(), args.strip()))
    assert not pending, "the Dockerfile ends in a continuation line"
    return out


def _exec_form(args: str) -> list[str]:
    value = json.loads(args)  # the exec form: a JSON array (signals reach the process itself)
    assert isinstance(value, list) and all(isinstance(v, str) for v in value)
    return value


def test_dockerfile() -> None:
    ins = dockerfile_instructions(DOCKERFILE.read_text())
    by = {}
    for word, args in ins:
        by.setdefault(word, []).append(args)
    assert by["FROM"][-1] == "python:3.11-slim-bookworm"  # the image; before it the viewer's node stage
    assert by["FROM"][:-1] == ["node:20-bookworm-slim AS viewer"]
    assert "--from=viewer /viewer/vendor /src/services/api/viewer/vendor" in by["COPY"]
    entrypoint = _exec_form(by["ENTRYPOINT"][-1])
    cmd = _exec_form(by["CMD"][-1]) if "CMD" in by else []
    assert entrypoint[0] == "citytherm" or (not entrypoint and cmd[0] == "citytherm")
    user = by["USER"][-1].split(":")[0]
    assert user not in ("root", "0"), "the image runs as a non-root user"
    assert "WORKDIR" in by
    env = " ".join(by.get("ENV", []))
    assert "CITYTHERM_STORAGE_DIR=/data" in env
    runs = " ".join(by["RUN"])
    for pkg in ("libusb-1.0-0", "libgomp1", "libgl1", "libglib2.0-0"):
        assert pkg in runs, f"{pkg} is not installed"
    assert "pip install" in runs and "[dev]" not in runs
    assert "npm ci --omit=dev" in runs and "node vendor.mjs" in runs  # the viewer's three.js modules


def test_dockerignore_keeps_the_build_inputs() -> None:
    """`pip install .` needs pyproject.toml, README.md (the readme) and the packages."""
    patterns = {
        line.strip().rstrip("/")
        for line in DOCKERIGNORE.read_text().splitlines()
        if line.strip() and not line.startswith("#")
    }
    assert {".git", ".venv", "demo-out"} <= patterns
    for needed in ("pyproject.toml", "README.md", "services", "workers", "db"):
        assert needed not in patterns, f".dockerignore excludes {needed}"
