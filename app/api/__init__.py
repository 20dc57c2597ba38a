"""The HTTP API: FastAPI routers (``routes/``) and pydantic schemas (``schemas/``); the
dependencies, errors and headers it shares with the dashboard are in ``app.web``.

It reads and writes only through ``app.services`` and ``app.storage``; ORM rows never reach it.
"""
