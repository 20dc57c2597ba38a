"""Keeping a job's lease alive while it runs, and the flags the job's runner checks.

    control = JobControl()
    with LeaseKeeper(db, lease, control=control, lease_s=30.0, heartbeat_s=5.0):
        run_job(db, lease, control=control, ...)     # checks control between stages

A :class:`LeaseKeeper` is a thread that renews the lease every ``heartbeat_s`` with
:func:`app.storage.queue.heartbeat`. It records what it learns in the :class:`JobControl`: that a
cancel was requested (the API wrote ``cancel_requested``) or that the lease is lost (it expired and
the job was requeued or claimed by another worker). The flags are plain attributes, so a signal
handler may set ``release_requested`` safely (no locks are taken).

The thread needs the GIL, which gtsam keeps for the whole of one Levenberg–Marquardt iteration
(≈ 0.3 s at 20,000 poses; milliseconds for a real session): ``lease_s − heartbeat_s`` must be
longer than that, as it is by far with the defaults (30 s and 5 s).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from types import TracebackType

from app.storage import queue
from app.storage.db import Database
from app.storage.queue import Lease, LeaseLost
from workers.failures import log_failure

logger = logging.getLogger(__name__)

#: How much earlier than ``lease_s`` after a renewal the worker counts its lease as gone, s.
LEASE_MARGIN_S = 1.0


class JobControl:
    """What the worker and its heartbeat thread tell the job's runner (checked between stages).

    cancel_requested: someone asked to cancel the job; it stops at the next stage boundary.
    lease_lost: the lease is gone; the job is abandoned and nothing more is written.
    release_requested: the worker is shutting down now; the job goes back to the queue at the next
        stage boundary, its attempt not counted.
    lease_deadline_s: until when (``time.monotonic()``) the lease holds without another renewal;
        the runner waits out a database outage only until then (``-inf``: no lease keeper, so it
        does not wait).
    """

    def __init__(self) -> None:
        self.cancel_requested = False
        self.lease_lost = False
        self.release_requested = False
        self.lease_deadline_s = -math.inf

    def __repr__(self) -> str:
        return (
            f"JobControl(cancel_requested={self.cancel_requested}, lease_lost={self.lease_lost}, "
            f"release_requested={self.release_requested})"
        )


class LeaseKeeper:
    """A daemon thread that renews ``lease`` every ``heartbeat_s`` until the block ends.

    ``on_beat`` (optional) is called after each successful renewal, e.g. to update the worker's own
    row. A failed renewal for any reason but :class:`LeaseLost` (the database briefly unreachable)
    is logged and tried again at the next beat; the lease survives as long as one renewal per
    ``lease_s`` gets through.
    """

    def __init__(
        self,
        db: Database,
        lease: Lease,
        *,
        control: JobControl,
        lease_s: float,
        heartbeat_s: float,
        on_beat: Callable[[], None] | None = None,
    ) -> None:
        self._db = db
        self._lease = lease
        self._control = control
        self._lease_s = lease_s
        self._heartbeat_s = heartbeat_s
        self._on_beat = on_beat
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"lease-keeper-job-{lease.job_id}", daemon=True
        )

    def __enter__(self) -> LeaseKeeper:
        self._renewed()  # the claim just gave a full lease
        self._thread.start()
        return self

    def _renewed(self) -> None:
        """The lease was just renewed: it holds ``lease_s`` from now (less a second, as the
        database's clock started counting a little earlier)."""
        self._control.lease_deadline_s = time.monotonic() + self._lease_s - LEASE_MARGIN_S

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        job_id = self._lease.job_id
        while not self._stop.wait(self._heartbeat_s):
            try:
                if queue.heartbeat(self._db, self._lease, lease_s=self._lease_s):
                    self._control.cancel_requested = True
                self._renewed()
            except LeaseLost:
                self._control.lease_lost = True
                return
            except Exception as err:
                log_failure(
                    logger,
                    f"job {job_id}: heartbeat failed; trying again in {self._heartbeat_s:g} s",
                    err,
                    extra={"action": "heartbeat_failed", "job_id": job_id},
                )
                continue
            if self._on_beat is not None:
                try:
                    self._on_beat()
                except Exception:
                    logger.warning("job %d: worker heartbeat failed", job_id, exc_info=True)
