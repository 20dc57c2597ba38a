"""``serve``'s supervision of its API processes, with stand-ins for the processes: a death is
replaced after the back-off, one that could not start stops serve (the real processes:
tests/cli/test_api_processes.py)."""

from __future__ import annotations

import socket
from dataclasses import dataclass, field

import pytest

from app.cli.api_processes import STARTUP_FAILED, ApiProcessSupervisor
from app.config import Settings
from workers.supervisor import FIRST_RESTART_S


@dataclass
class StandIn:
    pid: int
    exitcode: int | None = None
    joined: list[float] = field(default_factory=list)

    def is_alive(self) -> bool:
        return self.exitcode is None

    def join(self, timeout: float | None = None) -> None:
        self.joined.append(timeout or 0.0)


STARTED: list[StandIn] = []


@pytest.fixture
def supervisor(monkeypatch: pytest.MonkeyPatch) -> ApiProcessSupervisor:
    STARTED.clear()
    with socket.socket() as listener:
        api = ApiProcessSupervisor(
            Settings(database_url="sqlite://"), listener, processes=2, worker_status=None
        )
    pids = iter(range(100, 200))

    def start(slot, now_s):  # type: ignore[no-untyped-def]
        slot.process, slot.started_s, slot.restart_at_s = StandIn(next(pids)), now_s, None
        STARTED.append(slot.process)
        return slot.process

    monkeypatch.setattr(api, "_start", start)
    api.start()
    return api


def test_a_dead_api_process_is_replaced_after_the_back_off(supervisor, caplog):
    first = list(supervisor.pids)
    STARTED[0].exitcode = -9  # api-1 is killed
    supervisor.tend(now_s=1000.0)
    assert supervisor.pids == first[1:]  # reaped, not yet replaced
    supervisor.tend(now_s=1000.0 + FIRST_RESTART_S)
    assert len(supervisor.pids) == 2
    assert first[0] not in supervisor.pids
    assert supervisor.restarts == 1
    assert supervisor.failure is None
    assert "API process api-1 (pid 100) killed by SIGKILL" in caplog.text


def test_an_api_process_that_could_not_start_stops_serve(supervisor):
    STARTED[1].exitcode = STARTUP_FAILED
    supervisor.tend(now_s=1000.0)
    assert supervisor.failure is not None
    assert "api-2 (pid 101) could not start" in supervisor.failure
    assert supervisor.restarts == 0
