"""Freeing the apps the tests make.

FastAPI (0.165) remembers, in three module-level LRU caches of 4,096 entries each, whether each
endpoint and dependency it has seen is a coroutine or a generator, keyed by the callable itself.
Our endpoints are closures over their app, so those caches keep the last few dozen apps the
tests made alive: 2.1 M objects after the 90 tests of ``tests/service/test_api_navigation.py``,
and every full garbage collection then took 4 s (that file ran in 166 s; 102 s once the caches
are forgotten after each test, with 0.4 M objects left). A server makes its one app at start, so
only the tests pay this; ``tests/conftest.py`` forgets the caches after every test, and
``tests/unit/test_fastapi_caches.py`` checks that doing so frees an app.
"""

from __future__ import annotations

#: The caches, in ``fastapi.dependencies.models`` (private names: another FastAPI may lack them,
#: and then the test of this module says so).
CACHED_CLASSIFIERS = (
    "_is_gen_callable_cached",
    "_is_async_gen_callable_cached",
    "_is_coroutine_callable_cached",
)


def forget_fastapi_caches() -> int:
    """Clear FastAPI's caches of callables; how many of them there were."""
    from fastapi.dependencies import models

    found = 0
    for name in CACHED_CLASSIFIERS:
        cached = getattr(models, name, None)
        if cached is not None:
            cached.cache_clear()
            found += 1
    return found
