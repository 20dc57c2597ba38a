"""An app the tests made and dropped is freed once FastAPI's caches are forgotten (the reason
is in ``tests/fastapi_caches.py``): what keeps every service test's garbage collections short."""

from __future__ import annotations

import gc
import weakref

from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app
from tests.fastapi_caches import CACHED_CLASSIFIERS, forget_fastapi_caches


def _dropped_app(tmp_path) -> weakref.ref:  # type: ignore[no-untyped-def]
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'app.sqlite3'}")
    app = create_app(settings)
    with TestClient(app) as client:
        assert client.get("/healthz").status_code == 200
    return weakref.ref(app)


def test_every_cache_is_where_fastapi_keeps_it() -> None:
    assert forget_fastapi_caches() == len(CACHED_CLASSIFIERS)


def test_an_app_is_freed_once_the_caches_are_forgotten(tmp_path) -> None:  # type: ignore[no-untyped-def]
    app = _dropped_app(tmp_path)
    gc.collect()
    assert app() is not None, "FastAPI no longer keeps apps alive: tests/fastapi_caches.py can go"
    forget_fastapi_caches()
    gc.collect()
    assert app() is None, [type(r).__name__ for r in gc.get_referrers(app())]
