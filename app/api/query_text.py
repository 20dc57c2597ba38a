"""Query strings the database cannot hold are refused at the door (issue 19, finding 7).

A NUL character (``%00``) in a query parameter reached PostgreSQL as a search pattern and failed
there (500: text cannot contain NUL). Every parameter of every route (the API's and the
dashboard's) is checked once, before its route runs, by the rule every stored text follows
(:func:`app.domain.upload.fields.text_fault`): a NUL (or a lone surrogate, should one ever get
through the URL decoding, which turns invalid UTF-8 into U+FFFD) is a 422 naming the parameter.
Path ids are integers, which FastAPI already refuses with the parameter's name.
"""

from __future__ import annotations

from fastapi import Request
from fastapi.exceptions import RequestValidationError

from app.domain.upload.fields import text_fault


async def refuse_unstorable_query(request: Request) -> None:
    """The app's dependency: RequestValidationError (422, the parameter named) for a query
    parameter's name or value that the database could not hold."""
    for name, value in request.query_params.multi_items():
        why = text_fault(name) or text_fault(value)
        if why is not None:
            raise RequestValidationError(
                [
                    {
                        "loc": ("query", name),
                        "msg": f"the query parameter {why}",
                        "type": "value_error",
                    }
                ]
            )
