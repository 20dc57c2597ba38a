"""What the API and the dashboard both do, over storage and the domain: one module per resource.

Routers (``app.api``) and pages (``app.admin``) call these and translate their answers and errors
into HTTP or HTML; neither imports the other. Errors are :mod:`app.services.errors`.
"""
