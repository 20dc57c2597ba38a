"""What the command-line tests share: how a command's error must look."""

from __future__ import annotations

ERROR_PREFIX = "invisible-map: error:"


def assert_one_line_error(status: int, stderr: str, *parts: str) -> str:
    """A failure on bad input: exit status 1, one line ``invisible-map: error: …`` holding each of
    ``parts``, no traceback. Returns the line."""
    assert status == 1, stderr
    assert "Traceback" not in stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith(ERROR_PREFIX), lines[0]
    for part in parts:
        assert part in lines[0], f"{part!r} not in {lines[0]!r}"
    return lines[0]
