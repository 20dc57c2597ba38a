"""docker-compose.yml and the Dockerfile, checked with parsers (no Docker engine runs here)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

from app.admin.signing import Signer, load_or_create_secret
from app.cli import program as cli_program
from app.config import Settings
from workers import allocator

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    document = yaml.safe_load((REPO_ROOT / "docker-compose.yml").read_text())
    assert isinstance(document, dict)
    return document


@pytest.fixture(scope="module")
def services(compose: dict[str, Any]) -> dict[str, Any]:
    return compose["services"]


def test_the_four_services_are_there(services):
    assert set(services) == {"postgres", "migrate", "api", "worker"}


def test_postgres_is_health_checked_and_persistent(compose, services):
    postgres = services["postgres"]
    assert "pg_isready" in " ".join(postgres["healthcheck"]["test"])
    assert any(volume.startswith("pgdata:") for volume in postgres["volumes"])
    assert "pgdata" in compose["volumes"]


def test_migration_runs_once_after_postgres_is_healthy(services):
    migrate = services["migrate"]
    assert migrate["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert migrate["restart"] == "no"
    assert migrate["command"][:2] == ["invisible-map", "migrate"]


@pytest.mark.parametrize("name", ["api", "worker"])
def test_api_and_workers_wait_for_the_migration(services, name):
    condition = services[name]["depends_on"]["migrate"]["condition"]
    assert condition == "service_completed_successfully"


def test_worker_can_be_scaled(services):
    worker = services["worker"]
    # `--scale worker=N` needs no fixed container name and no published host port.
    assert "container_name" not in worker
    assert "ports" not in worker
    assert worker["command"][:2] == ["invisible-map", "worker"]


def test_api_does_not_start_its_own_workers_or_migrate(services):
    command = services["api"]["command"]
    args = cli_program._parser().parse_args(command[1:])
    assert args.command == "serve"
    assert args.workers == 0
    assert args.no_migrate
    assert args.host == "0.0.0.0"
    assert services["api"]["ports"] == [f"{args.port}:{args.port}"]


@pytest.mark.parametrize("name", ["migrate", "api", "worker"])
def test_commands_parse_with_our_command_line(services, name):
    command = services[name]["command"]
    assert command[0] == "invisible-map"
    cli_program._parser().parse_args(command[1:])  # exits (SystemExit) if not


@pytest.mark.parametrize("name", ["migrate", "api", "worker"])
def test_every_app_service_uses_postgres_through_psycopg(services, name):
    url = services[name]["environment"]["DATABASE_URL"]
    assert url.startswith("postgresql+psycopg://")
    assert "@postgres:5432/" in url
    settings = Settings(database_url=_interpolate(url))
    assert settings.resolved_database_url.startswith("postgresql+psycopg://")
    assert not settings.is_sqlite


def test_secrets_are_required_not_defaulted(services):
    assert services["api"]["environment"]["INVISIBLE_MAP_ADMIN_KEY"].startswith(
        "${INVISIBLE_MAP_ADMIN_KEY:?"
    )
    assert services["postgres"]["environment"]["POSTGRES_PASSWORD"].startswith(
        "${POSTGRES_PASSWORD:?"
    )


def test_every_api_container_signs_logins_with_one_secret_it_is_given(services):
    """Issue 28, finding 9: without INVISIBLE_MAP_SESSION_SECRET each API container made its own
    secret in its own data directory, so a recreated container logged every operator out and a
    second one did not accept the first one's logins."""
    secret = services["api"]["environment"]["INVISIBLE_MAP_SESSION_SECRET"]
    assert secret.startswith("${INVISIBLE_MAP_SESSION_SECRET:?")  # required, never in the file


def test_a_login_made_by_one_api_container_opens_the_dashboard_of_another(services, tmp_path):
    """Two API containers as the compose file makes them (each its own data directory, the
    environment the same): a cookie one signs, the other reads."""
    environment = {
        name: _interpolate(value, secret="s" * 64)
        for name, value in services["api"]["environment"].items()
        if name.startswith("INVISIBLE_MAP_")
    }
    signers = [
        Signer(load_or_create_secret(Settings(**_settings_fields(environment), data_dir=folder)))
        for folder in (tmp_path / "api-1", tmp_path / "api-2")
    ]
    token = signers[0].sign("login", {"sid": "abc"}, ttl_s=60)
    read = signers[1].unsign("login", token)
    assert read is not None
    assert read["sid"] == "abc"


def test_the_apis_data_directory_outlives_its_container(compose, services):
    data_dir = _dockerfile_env()["INVISIBLE_MAP_DATA_DIR"]
    mounts = dict(volume.split(":", 1) for volume in services["api"]["volumes"])
    named = {name for name, target in mounts.items() if target == data_dir}
    assert named, f"no volume at {data_dir}"
    assert named <= set(compose["volumes"])  # a named volume, not the container's own layer


def test_one_image_built_once(services):
    assert services["migrate"]["build"] == "."
    images = {services[name]["image"] for name in ("migrate", "api", "worker")}
    assert images == {"invisible-map:latest"}


def test_dockerfile_installs_the_project_and_runs_unprivileged():
    dockerfile = (REPO_ROOT / "Dockerfile").read_text()
    instructions = [
        line.split(None, 1)
        for line in _logical_lines(dockerfile)
        if line and not line.startswith("#")
    ]
    keywords = [keyword.upper() for keyword, *_ in instructions]
    assert keywords[0] == "FROM"
    assert re.match(r"python:3\.1[1-9]", instructions[0][1])
    copied = {shlex.split(rest)[0] for keyword, rest in instructions if keyword == "COPY"}
    assert {"app", "workers", "migrations", "data"} <= copied
    assert any(keyword == "RUN" and "pip install" in rest for keyword, rest in instructions)
    users = [rest for keyword, rest in instructions if keyword == "USER"]
    assert users
    assert users[-1] != "root"
    cmd = next(rest for keyword, rest in instructions if keyword == "CMD")
    assert "invisible-map" in cmd


def test_the_worker_preloads_the_jemalloc_the_image_links():
    """The compose worker runs one process, which cannot preload jemalloc itself
    (``workers/allocator.py``): the image installs it and links it where the worker's LD_PRELOAD
    points, and where ``workers.allocator`` looks for it."""
    dockerfile = (REPO_ROOT / "Dockerfile").read_text()
    worker = yaml.safe_load((REPO_ROOT / "docker-compose.yml").read_text())["services"]["worker"]
    preload = worker["environment"]["LD_PRELOAD"]
    run = next(line for line in _logical_lines(dockerfile) if "libjemalloc2" in line)
    assert run.startswith("RUN ")
    assert "apt-get install" in run
    assert run.rstrip().endswith(preload)
    assert preload in allocator.JEMALLOC_PATHS


def _logical_lines(text: str) -> list[str]:
    return [line.strip() for line in text.replace("\\\n", " ").splitlines()]


def _interpolate(value: str, *, secret: str = "secret") -> str:
    return re.sub(r"\$\{[^}]*\}", secret, value)


def _settings_fields(environment: dict[str, str]) -> dict[str, str]:
    """Settings' fields from ``INVISIBLE_MAP_*`` variables."""
    return {
        name.removeprefix("INVISIBLE_MAP_").lower(): value for name, value in environment.items()
    }


def _dockerfile_env() -> dict[str, str]:
    """The image's ENV variables."""
    found: dict[str, str] = {}
    for line in _logical_lines((REPO_ROOT / "Dockerfile").read_text()):
        if line.upper().startswith("ENV "):
            for pair in shlex.split(line[4:]):
                name, _, value = pair.partition("=")
                found[name] = value
    return found
