"""Who is logged in to the dashboard, and the checks every request and form goes through.

Logging in takes an admin API key (a key with role admin, or ``INVISIBLE_MAP_ADMIN_KEY``); a
device key is refused. The login is a row of ``admin_login`` (:mod:`app.storage.admin_logins`)
and a signed cookie (:mod:`app.admin.signing`) carrying its token, the key's identity, a random
nonce and an expiry. On every request both are checked again: a login ended since (logout,
"end all dashboard sessions", the key revoked) or a key revoked or expired since (or a changed
``INVISIBLE_MAP_ADMIN_KEY``) is no login, so a cookie copied before logout opens nothing.

    user: DashboardUserDep          # a page: 303 to /admin/login?next=… without a valid login
    form: CheckedFormDep            # a form post: the login, then its CSRF token (403 if wrong)

CSRF: every form carries ``csrf_token``, an HMAC of the login's nonce, checked against the cookie
(synchronizer token; the cookie is also ``SameSite=Strict``). The login form itself, made before
there is a login, uses a double-submit cookie. Guessing is slowed per client address and in all
(:class:`LoginThrottle`, in memory per process): an attempt may be held before its key is
checked, but a key is never refused for what others tried.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import secrets
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated
from urllib.parse import quote

from fastapi import Depends, Request, Response
from fastapi.exceptions import RequestValidationError
from starlette.datastructures import FormData
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from app.admin.signing import Signer, load_or_create_secret
from app.config import Settings
from app.domain.upload.fields import text_fault
from app.storage import admin_logins, keys
from app.storage.db import Database
from app.storage.keys import ENVIRONMENT_ADMIN, Principal
from app.storage.orm import Role
from app.web.deps import DbDep, SettingsDep

logger = logging.getLogger(__name__)

LOGIN_COOKIE = "im_admin_login"
LOGIN_FORM_COOKIE = "im_admin_login_form"
COOKIE_PATH = "/admin"
#: How long a dashboard login lasts, s.
LOGIN_TTL_S = 8 * 3600
#: How long the login form's CSRF cookie lasts, s.
LOGIN_FORM_TTL_S = 3600
#: Failed logins a minute from one source (client address) before its attempts are slowed
#: (:class:`LoginThrottle`).
LOGIN_FREE_FAILURES_PER_SOURCE = 10
#: Failed logins a minute from all sources before every attempt is slowed, per API process.
LOGIN_FREE_FAILURES_OVERALL = 100
LOGIN_WINDOW_S = 60.0
#: The hold of the first slowed attempt, s; it doubles with each failure beyond the free ones
#: (from one source; from all, with each ten).
LOGIN_FIRST_HOLD_S = 0.25
#: The longest an attempt is held before its key is checked, s: what a correct key may wait
#: while someone guesses, never a refusal.
LOGIN_MAX_HOLD_S = 5.0


class LoginRequired(Exception):
    """Raised when a page needs a login and the request has none (or one no longer valid);
    answered with 303 to the login page, ``next`` being where to come back to."""

    def __init__(self, next_url: str) -> None:
        super().__init__("login required")
        self.next_url = next_url

    @property
    def login_url(self) -> str:
        return f"{COOKIE_PATH}/login?next={quote(self.next_url, safe='/')}"


class CsrfRefused(Exception):
    """Raised when a form arrives without the CSRF token of the login that made it (403)."""


class LoginThrottle:
    """Slows down guessing of admin keys without ever refusing a key: an attempt may be *held*
    before its key is checked, never answered without the check, so a correct key always logs
    in, at worst ``max_hold_s`` later.

    - **Per source** (the client address, as the server believes it: forwarded headers only from
      ``INVISIBLE_MAP_TRUSTED_PROXIES``): after ``free_per_source`` failed logins in
      ``window_s``, each attempt from that source is held ``first_hold_s``, doubling with each
      further failure, up to ``max_hold_s``.
    - **Globally** (all sources, this API process): after ``free_overall`` failures in
      ``window_s``, every attempt is held ``first_hold_s``, doubling with every ten further
      failures, up to ``max_hold_s`` (an attempt is held by the longer of the two).

    A guesser sending one attempt after another from one source gets at most one check per
    ``max_hold_s`` (12 a minute) once slowed; one holding C connections open at once, C per
    ``max_hold_s`` (connections per address are capped by ``INVISIBLE_MAP_MAX_CONNECTIONS_PER_
    ADDRESS``). Against keys of 192 random bits (a stored key's secret) or a long
    ``INVISIBLE_MAP_ADMIN_KEY``, that is no chance at all, and nobody else's attempts are
    refused: the lockout it replaces (ten wrong keys from anyone locking the right key out for a
    minute, issue 28) is gone. Holds are awaited on the event loop, no thread waits.

    Memory is bounded: at most ``max_sources`` sources are remembered (the least recently failed
    forgotten first) and ``max_failures`` failures per source and in all (a count beyond them
    holds the longest anyway)."""

    def __init__(
        self,
        *,
        free_per_source: int = LOGIN_FREE_FAILURES_PER_SOURCE,
        free_overall: int = LOGIN_FREE_FAILURES_OVERALL,
        window_s: float = LOGIN_WINDOW_S,
        first_hold_s: float = LOGIN_FIRST_HOLD_S,
        max_hold_s: float = LOGIN_MAX_HOLD_S,
        max_sources: int = 10_000,
        max_failures: int = 1_000,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.free_per_source = free_per_source
        self.free_overall = free_overall
        self.window_s = window_s
        self.first_hold_s = first_hold_s
        self.max_hold_s = max_hold_s
        self.max_sources = max_sources
        self.max_failures = max_failures
        self._clock = clock
        self._by_source: OrderedDict[str, deque[float]] = OrderedDict()
        self._all: deque[float] = deque()
        self._lock = threading.Lock()

    def hold_s(self, source: str) -> float:
        """How long an attempt from ``source`` is held before its key is checked, s."""
        now_s = self._clock()
        with self._lock:
            self._forget(now_s)
            times = self._by_source.get(source, deque())
            while times and times[0] <= now_s - self.window_s:
                times.popleft()
            from_source, overall = len(times), len(self._all)
        return max(
            self._hold(from_source - self.free_per_source, 1),
            self._hold(overall - self.free_overall, 10),
        )

    def failed(self, source: str) -> None:
        """Record a failed attempt from ``source``."""
        now_s = self._clock()
        with self._lock:
            times = self._by_source.pop(source, None) or deque(maxlen=self.max_failures)
            times.append(now_s)
            self._by_source[source] = times  # the most recent last
            while len(self._by_source) > self.max_sources:
                self._by_source.popitem(last=False)
            self._all.append(now_s)
            while len(self._all) > self.max_failures:
                self._all.popleft()

    def _hold(self, beyond_free: int, per_doubling: int) -> float:
        if beyond_free < 0:
            return 0.0
        doublings = min(beyond_free // per_doubling, 64)
        return min(self.max_hold_s, self.first_hold_s * 2.0**doublings)

    def _forget(self, now_s: float) -> None:
        """Drop the failures older than the window: in all, and every source whose last failure
        is (sources are kept in the order of their last failure, so this stops at the first
        source still remembered: the cost is what is forgotten)."""
        horizon_s = now_s - self.window_s
        while self._all and self._all[0] <= horizon_s:
            self._all.popleft()
        while self._by_source:
            oldest = next(iter(self._by_source))
            times = self._by_source[oldest]
            if times and times[-1] > horizon_s:
                break
            del self._by_source[oldest]


class AdminState:
    """What the dashboard keeps per process: the signer and the login throttle."""

    def __init__(self, settings: Settings) -> None:
        self.signer = Signer(load_or_create_secret(settings))
        self.throttle = LoginThrottle()


_state_lock = threading.Lock()


def admin_state(request: Request) -> AdminState:
    """The app's :class:`AdminState`, made on first use."""
    app_state = request.app.state
    with _state_lock:
        state: AdminState | None = getattr(app_state, "admin", None)
        if state is None:
            state = AdminState(app_state.settings)
            app_state.admin = state
    return state


AdminStateDep = Annotated[AdminState, Depends(admin_state)]


def login_source(request: Request) -> str:
    """Where a login attempt comes from: the client's address (behind a trusted proxy, the one
    it forwards), or "unknown"."""
    return request.client.host if request.client is not None else "unknown"


async def hold_login(request: Request, state: AdminStateDep) -> None:
    """The login form's dependency: wait as long as :meth:`LoginThrottle.hold_s` says before the
    key is checked (on the event loop: no thread waits)."""
    hold_s = state.throttle.hold_s(login_source(request))
    if hold_s > 0:
        await asyncio.sleep(hold_s)


LoginHoldDep = Annotated[None, Depends(hold_login)]


@dataclass(frozen=True, slots=True, kw_only=True)
class DashboardUser:
    """A logged-in admin: who, and the CSRF token its forms must carry."""

    principal: Principal
    csrf_token: str

    @property
    def label(self) -> str:
        """How the page names who is logged in."""
        subject = self.principal.subject
        return "the server's admin key" if subject == ENVIRONMENT_ADMIN else f"API key {subject}"


# --------------------------------------------------------------------------- logging in and out


def start_login(
    response: Response,
    request: Request,
    state: AdminState,
    db: Database,
    principal: Principal,
    key: str,
) -> None:
    """Store a login of ``principal``, who logged in with ``key``, and set its cookie. The cookie
    carries the login's token and names a stored key by id; the environment's admin key (which
    has none) by a keyed fingerprint."""
    with db.transaction() as db_session:
        login_token = admin_logins.start_login(
            db_session, subject=principal.subject, key_id=principal.key_id, ttl_s=LOGIN_TTL_S
        )
    payload = {
        "sub": principal.subject,
        "kid": principal.key_id,
        "sid": login_token,
        "nonce": secrets.token_hex(16),
    }
    if principal.key_id is None:
        payload["fp"] = state.signer.fingerprint(key)
    token = state.signer.sign("login", payload, ttl_s=LOGIN_TTL_S)
    set_cookie(response, request, LOGIN_COOKIE, token, max_age_s=LOGIN_TTL_S)


def end_login(response: Response, request: Request, state: AdminState, db: Database) -> None:
    """End the request's login on the server (its cookie opens nothing from now on) and drop the
    cookie."""
    payload = state.signer.unsign("login", request.cookies.get(LOGIN_COOKIE))
    login_token = None if payload is None else payload.get("sid")
    if isinstance(login_token, str):
        with db.transaction() as db_session:
            admin_logins.end_login(db_session, login_token)
    response.delete_cookie(LOGIN_COOKIE, path=COOKIE_PATH, httponly=True, samesite="strict")


def set_cookie(
    response: Response, request: Request, name: str, value: str, *, max_age_s: int
) -> None:
    """A dashboard cookie: HttpOnly, SameSite=Strict, path /admin, Secure over https."""
    response.set_cookie(
        name,
        value,
        max_age=max_age_s,
        path=COOKIE_PATH,
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
    )


def login_form_token(request: Request, state: AdminState) -> str:
    """The login form's CSRF token: the one in its cookie if still valid, else a new one (the
    caller sets it with :func:`set_login_form_cookie`)."""
    payload = state.signer.unsign("login-form", request.cookies.get(LOGIN_FORM_COOKIE))
    if payload is not None and isinstance(payload.get("token"), str):
        return str(payload["token"])
    return secrets.token_hex(16)


def set_login_form_cookie(
    response: Response, request: Request, state: AdminState, token: str
) -> None:
    signed = state.signer.sign("login-form", {"token": token}, ttl_s=LOGIN_FORM_TTL_S)
    set_cookie(response, request, LOGIN_FORM_COOKIE, signed, max_age_s=LOGIN_FORM_TTL_S)


def login_form_token_ok(request: Request, state: AdminState, submitted: object) -> bool:
    """Whether a login form carries the token of its cookie (double submit)."""
    payload = state.signer.unsign("login-form", request.cookies.get(LOGIN_FORM_COOKIE))
    if payload is None or not isinstance(submitted, str):
        return False
    return hmac.compare_digest(str(payload.get("token", "")), submitted)


# --------------------------------------------------------------------------- every request


def dashboard_user(
    request: Request, state: AdminStateDep, settings: SettingsDep, db: DbDep
) -> DashboardUser:
    """The logged-in admin, checked again against the keys; LoginRequired otherwise."""
    payload = state.signer.unsign("login", request.cookies.get(LOGIN_COOKIE))
    principal = None if payload is None else _still_valid(payload, state, settings, db)
    if principal is None or payload is None:
        raise LoginRequired(_here(request))
    user = DashboardUser(
        principal=principal, csrf_token=state.signer.csrf_token(str(payload.get("nonce", "")))
    )
    request.state.admin_user = user
    return user


def _still_valid(
    payload: dict[str, object], state: AdminState, settings: Settings, db: Database
) -> Principal | None:
    """The principal the login cookie's payload stands for, if its login has not ended and its
    key still works."""
    login_token, key_id = payload.get("sid"), payload.get("kid")
    if not isinstance(login_token, str):
        return None
    with db.read() as db_session:
        login = admin_logins.find_login(db_session, login_token)
        if login is None or login.key_id != key_id or login.subject != payload.get("sub"):
            return None
        principal = (
            None if login.key_id is None else keys.active_principal(db_session, login.key_id)
        )
    if key_id is None:
        fingerprint = payload.get("fp")
        admin_key = settings.admin_key
        if payload.get("sub") != ENVIRONMENT_ADMIN or admin_key is None:
            return None
        if not isinstance(fingerprint, str):
            return None
        if not hmac.compare_digest(fingerprint, state.signer.fingerprint(admin_key)):
            return None
        return Principal(subject=ENVIRONMENT_ADMIN, role=Role.ADMIN)
    return principal if principal is not None and principal.is_admin else None


def _here(request: Request) -> str:
    """Where to come back to after logging in: this page (for a GET), else the overview."""
    if request.method != "GET":
        return COOKIE_PATH
    query = request.url.query
    return request.url.path + (f"?{query}" if query else "")


DashboardUserDep = Annotated[DashboardUser, Depends(dashboard_user)]


async def posted_form(request: Request) -> FormData:
    """The posted form, without a CSRF check (only the login form, which has no login yet,
    uses it); its text is checked (:func:`read_form`)."""
    return await read_form(request)


PostedFormDep = Annotated[FormData, Depends(posted_form)]


async def checked_form(request: Request, user: DashboardUserDep) -> FormData:
    """The posted form, if it carries the login's CSRF token; CsrfRefused (403) otherwise."""
    form = await read_form(request)
    token = form.get("csrf_token")
    if not isinstance(token, str) or not hmac.compare_digest(token, user.csrf_token):
        raise CsrfRefused("the form's security token is missing or wrong")
    return form


CheckedFormDep = Annotated[FormData, Depends(checked_form)]


async def read_form(request: Request) -> FormData:
    """The posted form. Every field's name and text value must be text a database can hold
    (:func:`app.domain.upload.fields.text_fault`, the rule of every stored text): a NUL is a
    422 naming the field (RequestValidationError, a page) before anything else happens. A client
    that disconnects while sending it is one line of the log (info) and a 400 nobody reads, not
    an unhandled error (issue 28, finding 5)."""
    try:
        form = await request.form()
    except ClientDisconnect:  # the browser went away while sending it: nobody to answer
        logger.info("client disconnected while sending %s %s", request.method, request.url.path)
        raise StarletteHTTPException(400, "the form did not arrive whole") from None
    for name, value in form.multi_items():
        reason = text_fault(name) or (text_fault(value) if isinstance(value, str) else None)
        if reason is not None:
            raise RequestValidationError(
                [{"loc": ("body", name), "msg": f"the field {reason}", "type": "value_error"}]
            )
    return form


def safe_next(next_url: str | None) -> str:
    """``next_url`` if it is a dashboard path on this site, else the overview."""
    if (
        next_url
        and next_url.startswith(COOKIE_PATH)
        and not next_url.startswith("//")
        and "\\" not in next_url
        and not next_url.startswith(f"{COOKIE_PATH}/login")
    ):
        return next_url
    return COOKIE_PATH
