"""A cancel reaches a running optimization within seconds, and a job past its time budget fails
for good with the reason (issue 19, finding 2): the optimizer's iteration callback checks the
job's flags (``JobContext.check_interrupted``). On SQLite and PostgreSQL."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
from api_support import ADMIN, running_api

from app.config import Settings
from app.domain.evaluation.tuning import TuningTarget
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session, trial
from app.domain.upload.session import decode_json_bytes, parse_session
from app.storage import queue
from app.storage.db import Database
from app.storage.orm import JobState
from tests.service.helpers import (
    get_job,
    insert_session,
    session_bytes,
    simulated_bytes,
    wait_for,
)
from workers import pipeline
from workers.main import Worker
from workers.pipeline import Interrupted

pytestmark = pytest.mark.db

#: The stand-in optimizer's iterations: 0.05 s each, 500 s in all unless stopped.
ITERATION_S = 0.05


def endless_optimizer(
    _session: Any, _params: Any, *, on_iteration: Callable[[int, float], None]
) -> Any:
    for iteration in range(10_000):
        on_iteration(iteration, 1.0)
        time.sleep(ITERATION_S)
    raise AssertionError("never stopped")


def worker(db: Database, **settings: float) -> Worker:
    values = {"lease_s": 5.0, "heartbeat_s": 0.5, "poll_s": 0.05, "retry_backoff_s": 0.0}
    url = db.url.render_as_string(hide_password=False)
    return Worker(db, Settings(database_url=url, **{**values, **settings}))


def test_a_cancel_stops_a_running_optimization_within_seconds(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(pipeline.build_map, "optimize_session", endless_optimizer)
    job_id = insert_session(db, session_bytes("onetag")).job_id
    thread = threading.Thread(target=worker(db).run_once)
    thread.start()
    wait_for(lambda: get_job(db, job_id).stage == "optimize", timeout_s=30, what="optimize")
    time.sleep(1.0)  # well inside the optimization
    asked_s = time.monotonic()
    with db.transaction() as db_session:
        queue.request_cancel(db_session, job_id)
    wait_for(
        lambda: get_job(db, job_id).state == JobState.CANCELED, timeout_s=10, what="the cancel"
    )
    latency_s = time.monotonic() - asked_s
    thread.join(10)
    print(f"cancel of a running optimization took effect after {latency_s:.2f} s")
    assert latency_s < 3.0  # a heartbeat (0.5 s) and an iteration
    assert "cancel requested: stopped during optimize" in get_job(db, job_id).log_tail


def test_a_job_past_its_time_budget_fails_once_with_the_reason(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(pipeline.build_map, "optimize_session", endless_optimizer)
    job_id = insert_session(db, session_bytes("onetag")).job_id
    started_s = time.monotonic()
    assert worker(db, job_time_budget_s=1.0).run_once()
    assert time.monotonic() - started_s < 10
    info = get_job(db, job_id)
    assert (info.state, info.attempts) == (JobState.FAILED, 1)
    assert info.error is not None
    assert "ran longer than its time budget of 1 s" in info.error


def test_the_iteration_callback_can_stop_gtsam() -> None:
    session = parse_session(decode_json_bytes(session_bytes("occam_room")))

    def stop(iteration: int, _error: float) -> None:
        if iteration >= 1:
            raise Interrupted("optimize")

    with pytest.raises(Interrupted):
        optimize_session(session, SlamParams(), on_iteration=stop)


def test_a_cancel_stops_a_running_sweep_job_between_trials(database_url: str) -> None:
    """A sweep's trials job stops after the trial it is running (each trial checks)."""
    with running_api(database_url) as api:
        created = api.uploaded(simulated_bytes(12_000))
        url = api.db.url.render_as_string(hide_password=False)
        build = Worker(api.db, Settings(database_url=url, lease_s=60, heartbeat_s=0.5))
        assert build.run_once()  # the map's first version
        space = {"odom_linear_var_m2_per_s": {"low": 1e-6, "high": 1e-1, "num": 20}}
        started = api.client.post(
            f"/v1/maps/{created['map_id']}/sweeps", json={"space": space}, headers=ADMIN
        )
        assert started.status_code == 202, started.text
        sweep_id = started.json()["sweep_id"]
        thread = threading.Thread(target=build.run_once)
        thread.start()

        def job_of_sweep() -> Any:
            jobs = api.client.get("/v1/jobs?state=running", headers=ADMIN).json()["data"]
            return next((j for j in jobs if j["kind"] == "sweep_trials"), None)

        wait_for(
            lambda: (job := job_of_sweep()) is not None and job["stage"] == "trials",
            timeout_s=60,
            what="the sweep's trials",
        )
        # (no pause: one job holds all 20 trials, done in about a second on this machine)
        running = job_of_sweep()
        asked_s = time.monotonic()
        cancel = api.client.post(f"/v1/sweeps/{sweep_id}/cancel", headers=ADMIN)
        assert cancel.status_code == 200, cancel.text
        wait_for(
            lambda: get_job(api.db, running["id"]).state == JobState.CANCELED,
            timeout_s=60,
            what="the trials job to stop",
        )
        latency_s = time.monotonic() - asked_s
        thread.join(30)
        print(f"cancel of a running sweep took effect after {latency_s:.2f} s")
        assert latency_s < 10


def test_the_iteration_callback_stops_a_trial_inside_its_optimization() -> None:
    """``TrialGraph.refine`` (one sweep trial: one Levenberg–Marquardt run) calls the callback
    after each iteration and stops where it raises; ``TuningTarget.run`` lets that through
    instead of recording a failed trial."""
    session = parse_session(decode_json_bytes(session_bytes("occam_room")))
    target = TuningTarget.prepare(session, SlamParams())
    values = {"odom_linear_var_m2_per_s": 1e-5}
    seen: list[int] = []

    def stop_at_1(iteration: int, _error: float) -> None:
        seen.append(iteration)
        if iteration >= 1:
            raise Interrupted("trials")

    with pytest.raises(Interrupted):  # the warm start, the first time
        target.run(values, on_iteration=stop_at_1)
    assert seen == [1]  # gtsam numbers its iterations from 1
    seen.clear()
    start = target.warm_start  # computed without a callback
    with pytest.raises(Interrupted):
        target.graph.refine(target.trial_params(values), start, on_iteration=stop_at_1)
    assert seen == [1]
    seen.clear()
    with pytest.raises(Interrupted):
        target.run(values, on_iteration=stop_at_1)
    assert seen == [1]
    finished = target.run(values, on_iteration=lambda i, _e: seen.append(i))
    assert finished.error is None
    assert len(seen) > 1  # every iteration of the whole trial


def endless_levenberg_marquardt(
    _graph: Any, _start: Any, _params: Any, on_iteration: Any, **_kwargs: Any
) -> Any:
    """A trial that would run 500 s: an iteration every 0.05 s, each calling back."""
    for iteration in range(1, 10_000):
        if on_iteration is not None:
            on_iteration(iteration, 1.0)
        time.sleep(ITERATION_S)
    raise AssertionError("never stopped")


def test_a_cancel_stops_a_running_sweep_inside_its_trial(
    database_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A cancel asked while a sweep's trials job is inside one long trial stops that trial
    within an iteration (before, the trial ran to its end first)."""
    with running_api(database_url) as api:
        created = api.uploaded(session_bytes("onetag"))
        url = api.db.url.render_as_string(hide_password=False)
        build = Worker(api.db, Settings(database_url=url, lease_s=60, heartbeat_s=0.5))
        assert build.run_once()  # the map's first version, with the real optimizer
        monkeypatch.setattr(trial, "levenberg_marquardt", endless_levenberg_marquardt)
        space = {"odom_linear_var_m2_per_s": {"low": 1e-6, "high": 1e-1, "num": 2}}
        started = api.client.post(
            f"/v1/maps/{created['map_id']}/sweeps", json={"space": space}, headers=ADMIN
        )
        assert started.status_code == 202, started.text
        thread = threading.Thread(target=build.run_once)
        thread.start()

        def running_trials() -> Any:
            jobs = api.client.get("/v1/jobs?state=running", headers=ADMIN).json()["data"]
            return next((j for j in jobs if j["kind"] == "sweep_trials"), None)

        job = wait_for(
            lambda: (
                (found := running_trials()) is not None and found["stage"] == "trials" and found
            ),
            timeout_s=60,
            what="the sweep's trials",
        )
        time.sleep(1.0)  # well inside the first trial
        cancel = api.client.post(f"/v1/sweeps/{started.json()['sweep_id']}/cancel", headers=ADMIN)
        assert cancel.status_code == 200, cancel.text
        wait_for(
            lambda: get_job(api.db, job["id"]).state == JobState.CANCELED,
            timeout_s=30,
            what="the trial to stop",
        )
        thread.join(30)
        assert not thread.is_alive()
        assert "cancel requested: stopped during trials" in get_job(api.db, job["id"]).log_tail
