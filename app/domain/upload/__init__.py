"""The upload: a mapping session as the phone sends it (docs/architecture.md §2), read once into
typed arrays.

    session.py          parse_session / load_session → Session (poses, detections, places)
    fields.py           readers of one field each, raising SessionFormatError with its path
    json_stream.py      one JSON document read from byte chunks in a bounded window
    earlier_format.py   the app's 2020–21 format, converted into the current one
"""
