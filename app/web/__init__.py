"""The HTTP plumbing the API (``app.api``) and the dashboard (``app.admin``) share, so that neither
imports the other:

    deps.py          the routes' dependencies (database, settings, keys, ids) as Annotated aliases
    errors.py        error answers: ApiError, the error body, the handlers for every error
    security.py      security headers and the pages' content security policy
    route_class.py   the route class that ends a request's transaction before its answer is sent
    http.py          entity tags, content negotiation, ready documents, a raw upload streamed
    upload.py        a request body read in bounded memory (gzip inflated with a limit)
"""
