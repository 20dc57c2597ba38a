"""The dashboard's pages, one module per menu entry (each has ``router = admin_router()``)."""
