"""The HTTP API: FastAPI routers (``routes/``), pydantic schemas, dependencies and errors.

It reads and writes only through ``app.storage``; ORM rows never reach it.
"""
