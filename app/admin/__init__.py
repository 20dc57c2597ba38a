"""The admin dashboard: server-rendered pages (Jinja2) under ``/admin`` with a little plain
JavaScript (live progress by polling, plots drawn by plotly.js served from the app).

    app/admin/router.py        the router create_app includes; the list of pages
    app/admin/nav.py           the menu (add a page: see there)
    app/admin/auth.py          login cookie, CSRF, login throttle
    app/admin/signing.py       signed values and the signing secret
    app/admin/routing.py       errors as pages, security headers
    app/admin/templating.py    rendering, flash messages
    app/admin/pages/*.py       one module per page
    app/admin/forms.py         the rebuild form's parameters, the route tester's endpoints
    app/domain/formats/map_figure.py   what the map page plots (made once per version)
"""
