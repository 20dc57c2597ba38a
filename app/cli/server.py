"""The server's subcommands of ``invisible-map``.

    invisible-map serve [--host H] [--port P] [--workers N] [--api-processes N] [--demo]
                        [--no-migrate] [--log-format text|json]
    invisible-map worker [--processes N] [--log-format text|json]
    invisible-map migrate
    invisible-map keys create --role device|admin [--name NAME] [--expires-in-days D]
    invisible-map keys list
    invisible-map keys revoke ID

All read their settings from the environment (``app/config.py``: ``DATABASE_URL``,
``INVISIBLE_MAP_DATA_DIR``, ``INVISIBLE_MAP_ADMIN_KEY``, …). Heavy imports (FastAPI, SQLAlchemy,
asyncio) happen inside the handlers so that the offline commands stay quick to start.
"""

from __future__ import annotations

import argparse
import errno
import logging
import secrets
import signal
import socket
import sys
import threading
import time
from datetime import timedelta
from typing import IO, TYPE_CHECKING, Any

from app.cli.common import (
    CommandError,
    load_settings,
    migrate_database,
    open_database,
    open_migrated,
    safe_url,
)
from workers.allocator import jemalloc_path

if TYPE_CHECKING:
    from app.client import Client
    from app.config import Settings
    from workers.supervisor import WorkerSupervisor


#: The longest ``keys create --expires-in-days`` (100 years).
MAX_KEY_DAYS = 36500
#: How often the demo asks whether its maps are built, s.
DEMO_POLL_S = 0.5
#: The largest id a row can have (a signed 64-bit integer).
MAX_ID = 2**63 - 1
#: The listening socket's queue of connections not yet accepted (uvicorn's default).
API_BACKLOG = 2048


def add_server_commands(commands: Any) -> None:
    """Register serve, worker, migrate and keys on the ``invisible-map`` subparsers."""
    serve = commands.add_parser(
        "serve",
        help="run the API, with its worker processes (embedded mode)",
        description="Run the REST API. Migrates the database first, starts --workers worker "
        "processes (default INVISIBLE_MAP_WORKERS, 1; --workers 0 runs the API alone) and "
        "--api-processes API processes on one port (default: one per core, at most 8).",
    )
    serve.add_argument("--host", default="127.0.0.1", help="interface to listen on (127.0.0.1)")
    serve.add_argument("--port", type=int, default=8000, help="port (8000)")
    serve.add_argument("--workers", type=int, help="worker processes to start with the API")
    serve.add_argument(
        "--api-processes",
        type=int,
        help="API processes sharing the port (default INVISIBLE_MAP_API_PROCESSES, else one per "
        "core, at most 8)",
    )
    serve.add_argument(
        "--demo", action="store_true", help="upload the demo sessions in data/ if not there yet"
    )
    serve.add_argument(
        "--no-migrate", action="store_true", help="do not run the migrations at start"
    )
    _add_log_format(serve)
    serve.set_defaults(handler=_serve)

    worker = commands.add_parser(
        "worker",
        help="run worker processes that take jobs from the database",
        description="Claim and run jobs from the database queue until SIGTERM (finish the "
        "current job) or a second SIGTERM (release it).",
    )
    worker.add_argument("--processes", type=int, default=1, help="worker processes (1)")
    _add_log_format(worker)
    worker.set_defaults(handler=_worker)

    migrate = commands.add_parser("migrate", help="bring the database schema up to date")
    migrate.set_defaults(handler=_migrate)

    keys = commands.add_parser("keys", help="create, list and revoke API keys")
    key_commands = keys.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    create = key_commands.add_parser("create", help="create a key and print it (shown once)")
    create.add_argument("--role", required=True, choices=["device", "admin"])
    create.add_argument("--name", default="", help="what the key is for")
    create.add_argument("--expires-in-days", type=float, help="expire the key after D days")
    create.set_defaults(handler=_keys_create)
    listing = key_commands.add_parser("list", help="list keys (never their secrets)")
    listing.set_defaults(handler=_keys_list)
    revoke = key_commands.add_parser("revoke", help="revoke a key by id")
    revoke.add_argument("key_id", type=int, metavar="ID")
    revoke.set_defaults(handler=_keys_revoke)


# --------------------------------------------------------------------------- helpers


def _add_log_format(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--log-format",
        choices=["text", "json"],
        help="the log: text (the default, INVISIBLE_MAP_LOG_FORMAT) or json, one JSON object "
        'per line (docs/operations.md, "Logs")',
    )


def _log_overrides(args: argparse.Namespace) -> dict[str, Any]:
    return {} if args.log_format is None else {"log_format": args.log_format}


# --------------------------------------------------------------------------- commands


def _serve(args: argparse.Namespace) -> int:
    import asyncio

    from app.config import MAX_API_PROCESSES, default_api_processes

    if not 0 < args.port < 65536:
        raise CommandError(f"--port must be 1–65535, got {args.port}")
    overrides: dict[str, Any] = _log_overrides(args)
    if args.workers is not None:
        if not 0 <= args.workers <= 64:
            raise CommandError(f"--workers must be 0–64, got {args.workers}")
        overrides["workers"] = args.workers
    if args.api_processes is not None:
        if not 1 <= args.api_processes <= MAX_API_PROCESSES:
            raise CommandError(
                f"--api-processes must be 1–{MAX_API_PROCESSES}, got {args.api_processes}"
            )
        overrides["api_processes"] = args.api_processes
    settings = load_settings(**overrides)
    if settings.log_format == "json":
        from app.observability.logs import configure_json_logging

        configure_json_logging()  # serve's own lines too, from here on
    api_processes = settings.api_processes or default_api_processes()
    # Each API process then knows how many share the database's connections (their pools).
    settings = settings.model_copy(update={"api_processes": api_processes})
    jemalloc_path()  # INVISIBLE_MAP_JEMALLOC: a path that is no file stops the command now
    listener = listening_socket(args.host, args.port)  # a busy port stops it before any output
    generated_key = settings.admin_key is None
    if generated_key:
        settings = settings.model_copy(
            update={"admin_key": "im_admin_" + secrets.token_urlsafe(24)}
        )
    try:
        database = open_database(settings)
        if not args.no_migrate:
            revision = migrate_database(database, settings)
            _say(f"database {safe_url(settings)} at revision {revision}")
        database.dispose()
    except BaseException:
        listener.close()
        raise

    # Imported only now (the worker pipeline, gtsam, matplotlib: ~1.5 s) so that a refused
    # option, setting or port answers at once.
    from workers.supervisor import WorkerSupervisor

    supervisor = WorkerSupervisor(settings, settings.workers)  # restarts any that dies
    supervisor.start()
    url = f"http://{args.host}:{args.port}"
    _say(f"Invisible Map server at {url}  (API docs: {url}/docs)", file=sys.stdout)
    if generated_key:
        _say(f"admin key for this run: {settings.admin_key}", file=sys.stdout)
        _say(
            "  (set INVISIBLE_MAP_ADMIN_KEY to choose one; `invisible-map keys create` for more)",
            file=sys.stdout,
        )
    _say(f"API processes: {api_processes}", file=sys.stdout)
    _say(f"worker processes: {supervisor.configured}", file=sys.stdout)
    if args.demo:
        assert settings.admin_key is not None
        threading.Thread(
            target=_upload_demo_sessions,
            args=(url, settings.admin_key, settings.workers),
            daemon=True,
        ).start()
    if api_processes > 1:
        return _serve_api_processes(settings, listener, supervisor, api_processes)
    from app.cli.api_processes import serve_with_threads, uvicorn_server

    server = uvicorn_server(settings, worker_pool=supervisor if settings.workers else None)
    # After its graceful shutdown uvicorn raises the SIGTERM that stopped it again, for the
    # previous handler: with the default one the process would die right there, before stopping
    # its workers (and exit by the signal). This handler makes that a no-op, and makes a SIGTERM
    # that comes before uvicorn installs its handlers stop it too.
    in_main_thread = threading.current_thread() is threading.main_thread()
    if in_main_thread:
        previous = signal.signal(signal.SIGTERM, lambda *_: setattr(server, "should_exit", True))
    try:
        # uvicorn's Server.run, with the thread pool sized first (it belongs to the event loop).
        with asyncio.Runner(loop_factory=server.config.get_loop_factory()) as runner:
            runner.run(serve_with_threads(server, settings.api_threads, listener))
    except SystemExit:  # uvicorn's sys.exit(3) when it cannot start (the port is taken, …)
        if server.started:
            raise
    finally:
        supervisor.stop(timeout_s=30.0)
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)
    if not server.started:
        raise CommandError(f"the server could not start at {url} (see the log above)")
    return 0


def _serve_api_processes(
    settings: Settings, listener: socket.socket, supervisor: WorkerSupervisor, processes: int
) -> int:
    """Run ``processes`` API processes on ``listener`` until SIGTERM or SIGINT, replacing any
    that dies (``app.cli.api_processes``); then stop them, then the worker processes."""
    from app.cli.api_processes import ApiProcessSupervisor, WorkerPoolStatus
    from app.observability.multiprocess import multiprocess_metrics
    from workers.main import configure_logging

    configure_logging(settings.log_format)  # the supervisors' lines (a death, a restart)
    listener.listen(API_BACKLOG)  # connections wait in the queue while no process accepts
    status = WorkerPoolStatus() if settings.workers else None
    if status is not None:
        status.publish(supervisor)
    api = ApiProcessSupervisor(settings, listener, processes=processes, worker_status=status)
    stop = threading.Event()
    in_main_thread = threading.current_thread() is threading.main_thread()
    if in_main_thread:
        previous = {
            signum: signal.signal(signum, lambda *_: stop.set())
            for signum in (signal.SIGTERM, signal.SIGINT)
        }
    try:
        # /metrics of any API process sums the request counts of all (app.observability)
        with multiprocess_metrics():
            try:
                api.start()
                api.run_until(
                    stop, tick=None if status is None else lambda: status.publish(supervisor)
                )
            finally:
                api.stop(timeout_s=30.0)
    finally:
        supervisor.stop(timeout_s=30.0)
        listener.close()
        if in_main_thread:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
    if api.failure is not None:
        raise CommandError(api.failure)
    return 0


def listening_socket(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host``:``port`` (uvicorn listens on it); CommandError naming the
    address if it cannot be had (in use, no such address, a privileged port)."""
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
    except socket.gaierror as err:
        raise CommandError(f"cannot listen on {host}:{port}: {err.strerror}") from err
    # IPPROTO_TCP, not 0: asyncio sets TCP_NODELAY only on sockets of that protocol, and without
    # it every response waits ~40 ms for the client's delayed acknowledgement.
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as err:
        sock.close()
        hint = "; stop what uses it or pass --port" if err.errno == errno.EADDRINUSE else ""
        raise CommandError(f"cannot listen on {host}:{port}: {err.strerror}{hint}") from err
    return sock


def _worker(args: argparse.Namespace) -> int:
    if not 1 <= args.processes <= 64:
        raise CommandError(f"--processes must be 1–64, got {args.processes}")
    settings = load_settings(**_log_overrides(args))
    jemalloc_path()  # INVISIBLE_MAP_JEMALLOC: a path that is no file stops the command now
    open_database(settings).dispose()
    from workers.main import run_worker_processes  # the pipeline: only once the checks pass

    return run_worker_processes(settings, args.processes)


def _migrate(_args: argparse.Namespace) -> int:
    settings = load_settings()
    database = open_database(settings)
    revision = migrate_database(database, settings)
    database.dispose()
    print(f"database {safe_url(settings)} at revision {revision}")
    return 0


def _keys_create(args: argparse.Namespace) -> int:
    from app.domain.upload.fields import text_fault
    from app.storage import keys
    from app.storage.orm import Role, utc_now

    if args.expires_in_days is not None and not 0 < args.expires_in_days <= MAX_KEY_DAYS:
        # (NaN fails the comparison; inf or more than MAX_KEY_DAYS would overflow a datetime)
        raise CommandError(
            f"--expires-in-days must be > 0 and at most {MAX_KEY_DAYS}, got {args.expires_in_days}"
        )
    if len(args.name) > 100:
        raise CommandError(f"--name is {len(args.name)} characters; at most 100")
    if (reason := text_fault(args.name)) is not None:  # e.g. bytes that are no UTF-8
        raise CommandError(f"--name {reason}")
    expires_at = utc_now() + timedelta(days=args.expires_in_days) if args.expires_in_days else None
    database = open_migrated(load_settings())
    with database.transaction() as db_session:
        info, secret = keys.create_key(
            db_session, name=args.name, role=Role(args.role), expires_at=expires_at
        )
    database.dispose()
    print(
        f"created {info.role.value} key {info.id}"
        + (f" ({info.name})" if info.name else "")
        + (f", expires {info.expires_at:%Y-%m-%d %H:%M} UTC" if info.expires_at else "")
        + "; it is shown only now:",
        file=sys.stderr,
    )
    print(secret)
    return 0


def _keys_list(_args: argparse.Namespace) -> int:
    from app.storage import keys
    from app.storage.orm import utc_now

    database = open_migrated(load_settings())
    with database.read() as db_session:
        rows = keys.list_keys(db_session)
    database.dispose()
    now = utc_now()
    for info in rows:
        if info.revoked_at is not None:
            status = "revoked"
        elif info.expires_at is not None and info.expires_at <= now:
            status = "expired"
        else:
            status = "active"
        print(f"{info.id}\t{info.role.value}\tim_{info.prefix}_…\t{status}\t{info.name}")
    if not rows:
        print("no API keys", file=sys.stderr)
    return 0


def _keys_revoke(args: argparse.Namespace) -> int:
    from app.storage import keys

    database = open_migrated(load_settings())
    try:
        if not 1 <= args.key_id <= MAX_ID:  # the database could not even compare it
            raise keys.KeyNotFound(args.key_id)
        with database.transaction() as db_session:
            info = keys.revoke_key(db_session, args.key_id)
    except keys.KeyNotFound as err:
        raise CommandError(str(err)) from err
    finally:
        database.dispose()
    print(f"revoked key {info.id} (im_{info.prefix}_…)")
    return 0


def _upload_demo_sessions(url: str, admin_key: str, workers: int) -> None:
    """Upload the demo sessions in data/ through the API once it is up, then say as each map
    becomes ready and, at the end, how many are. Idempotency keys make a restart find them
    instead of adding them again."""
    from app.cli.common import DATA_DIR, DEMO_POI_SESSION, DEMO_SESSIONS
    from app.client import ApiError, Client

    with Client(url, api_key=admin_key) as client:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                client.ready()
                break
            except Exception:  # not listening yet, or not ready
                time.sleep(0.2)
        demo_sessions = [
            (name, DATA_DIR / "sessions" / f"{name}.json") for name, _ in DEMO_SESSIONS
        ]
        # floor_2_straight with points of interest, for the README's quick start (data/README.md)
        demo_sessions.append((DEMO_POI_SESSION[0], DATA_DIR / "demo" / "floor_2_pois.json"))
        truth_files = dict([*DEMO_SESSIONS, DEMO_POI_SESSION])
        building: dict[int, tuple[str, int]] = {}  # job id → (name, map id)
        for name, path in demo_sessions:
            try:
                accepted = client.upload_session(path, idempotency_key=f"demo-{name}")
            except (ApiError, OSError) as err:
                _say(f"demo: {name} not uploaded: {err}")
                continue
            building[accepted["job_id"]] = (name, accepted["map_id"])
            _say(
                f"demo: {name}: session {accepted['session_id']}, map {accepted['map_id']}, "
                f"job {accepted['job_id']}"
            )
        if workers == 0:
            _say("demo: no worker processes (--workers 0): maps are built when a worker runs")
            return
        ready = _report_demo_maps(client, url, building)
        _attach_ground_truth(client, url, building, truth_files)
        _say(f"demo: {ready} of {len(demo_sessions)} maps ready: {url}/admin/maps")


def _report_demo_maps(client: Client, url: str, building: dict[int, tuple[str, int]]) -> int:
    """Say each demo map as its build ends (ready, or failed with the reason); the number ready.
    Stops quietly when the server stops answering (it is shutting down)."""
    from app.client import ApiError

    ready = 0
    pending = dict(building)
    while pending:
        for job_id, (name, map_id) in list(pending.items()):
            try:
                job = client.get_job(job_id)
            except (ApiError, OSError):
                return ready
            if job["state"] == "succeeded":
                ready += 1
                _say(f"demo: map {map_id} ({name}) ready: {url}/v1/maps/{map_id}")
            elif job["state"] in ("failed", "canceled"):
                _say(f"demo: map {map_id} ({name}) {job['state']}: {job.get('error') or ''}")
            else:
                continue
            del pending[job_id]
        time.sleep(DEMO_POLL_S)
    return ready


def _attach_ground_truth(
    client: Client,
    url: str,
    building: dict[int, tuple[str, int]],
    truth_files: dict[str, str | None],
) -> None:
    """Rebuild each demo map that has ground truth in data/ground_truth with it, so that its
    current version carries the ground-truth metric (on the map page and in the API); say each
    one's figures. A map whose current version has them already (a restart) is left alone."""
    from app.cli.common import DATA_DIR
    from app.client import ApiError
    from app.domain.evaluation.ground_truth import ground_truth_to_json, load_ground_truth

    rebuilding: dict[int, tuple[str, int, str]] = {}  # job id → (name, map id, truth file)
    for name, map_id in building.values():
        truth_file = truth_files.get(name)
        if truth_file is None:
            continue
        try:
            current = client.get_map(map_id)["current_version"]
            if current is None or "gt_metric_opt" in current["metrics"]:
                continue  # its build failed, or it has the metric already
            truth = ground_truth_to_json(load_ground_truth(DATA_DIR / "ground_truth" / truth_file))
            accepted = client.rebuild_map(map_id, current["params"], ground_truth=truth)
        except (ApiError, OSError) as err:
            _say(f"demo: map {map_id} ({name}): no ground truth attached: {err}")
            continue
        rebuilding[accepted["job_id"]] = (name, map_id, truth_file)
    while rebuilding:
        for job_id, (name, map_id, truth_file) in list(rebuilding.items()):
            try:
                job = client.get_job(job_id)
                if job["state"] not in ("succeeded", "failed", "canceled"):
                    continue
                metrics = client.get_map(map_id)["current_version"]["metrics"]
            except (ApiError, OSError):
                return  # the server is shutting down
            del rebuilding[job_id]
            if job["state"] != "succeeded" or "gt_metric_opt" not in metrics:
                _say(f"demo: map {map_id} ({name}): ground truth not attached: {job['state']}")
                continue
            _say(
                f"demo: map {map_id} ({name}) with ground truth ({truth_file}): ground-truth "
                f"metric {metrics['gt_metric_opt']:.4f} (pre-optimized "
                f"{metrics['gt_metric_pre']:.4f}), {metrics['tags_with_ground_truth']} tags: "
                f"{url}/admin/maps/{map_id}"
            )
        time.sleep(DEMO_POLL_S)


def _say(line: str, *, file: IO[str] | None = None) -> None:
    """Say ``line`` on stderr (or ``file``); with the JSON log, as a log record instead."""
    from app.observability.logs import json_logging_active

    if json_logging_active():
        logging.getLogger("app.cli.server").info(line)
    else:
        print(line, file=file or sys.stderr, flush=True)
