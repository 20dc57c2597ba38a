"""Every file a command reads is read with a bound, and what is no regular file (a FIFO, a device,
a folder) is refused at once, in one line (issue 40, finding 2: ``import --check /dev/zero`` read
6.75 GB before it was stopped, and a FIFO hung it). The commands run in this process; an alarm
ends a command that hangs, so that a regression fails instead of hanging the suite."""

from __future__ import annotations

import gzip
import os
import resource
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import pytest
from cli_support import assert_one_line_error

from app import cli
from app.cli import common
from tests.read_counting import ReadCounting

ONETAG = Path(__file__).resolve().parents[2] / "data" / "sessions" / "onetag.json"
GROUND_TRUTH = Path(__file__).resolve().parents[2] / "data" / "ground_truth" / "rtabmap_mac_1_2.txt"


class Hung(Exception):
    """Raised by the alarm in a command that did not answer in time."""


@pytest.fixture
def no_hang() -> Iterator[None]:
    """An alarm after 10 s, and at most 2 GiB more address space for this process: a command
    that hangs fails, and one reading ``/dev/zero`` without end fails with a MemoryError instead
    of taking the machine's memory."""

    def alarm(_signal: int, _frame: FrameType | None) -> None:
        raise Hung("the command hung")

    previous = signal.signal(signal.SIGALRM, alarm)
    limits = resource.getrlimit(resource.RLIMIT_AS)
    status = Path("/proc/self/status").read_text()
    used_bytes = int(status.split("VmSize:")[1].split()[0]) * 1024
    resource.setrlimit(resource.RLIMIT_AS, (used_bytes + 2 * 2**30, limits[1]))
    signal.alarm(10)
    yield
    signal.alarm(0)
    resource.setrlimit(resource.RLIMIT_AS, limits)
    signal.signal(signal.SIGALRM, previous)


@pytest.fixture
def run(
    capsys: pytest.CaptureFixture[str],
    env: pytest.MonkeyPatch,
    tmp_path: Path,
    no_hang: None,  # noqa: ARG001
) -> Callable[..., tuple[int, str, str]]:
    env.setenv("DATABASE_URL", f"sqlite:///{tmp_path / 'unused.sqlite3'}")

    def run_main(*args: Any) -> tuple[int, str, str]:
        capsys.readouterr()
        status = cli.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return status, out, err

    return run_main


#: name → the command given a FIFO and a folder (each refused at once)
NOT_REGULAR: dict[str, Callable[[Path, Path], list[Any]]] = {
    "process: a FIFO": lambda fifo, _d: ["process", fifo],
    "process: /dev/zero": lambda _f, _d: ["process", "/dev/zero"],
    "process: a folder": lambda _f, folder: ["process", folder],
    "process --gt: a FIFO": lambda fifo, _d: ["process", ONETAG, "--gt", fifo],
    "evaluate --gt: /dev/zero": lambda _f, _d: ["evaluate", ONETAG, "--gt", "/dev/zero"],
    "evaluate: a FIFO": lambda fifo, _d: ["evaluate", fifo, "--gt", GROUND_TRUTH],
    "sweep --space: a FIFO": lambda fifo, _d: ["sweep", ONETAG, "--space", fifo],
    "simulate --from-session: /dev/zero": lambda _f, folder: [
        "simulate", folder / "out.json", "--from-session", "/dev/zero"
    ],
    "import --check: /dev/zero": lambda _f, _d: ["import", "--check", "/dev/zero"],
    "import --check: a FIFO": lambda fifo, _d: ["import", "--check", fifo],
    "import: a FIFO": lambda fifo, _d: ["import", fifo],
    "import: /dev/zero": lambda _f, _d: ["import", "/dev/zero"],
    "import: a folder": lambda _f, folder: ["import", folder],
}  # fmt: skip


@pytest.mark.parametrize("case", NOT_REGULAR)
def test_a_fifo_a_device_or_a_folder_is_refused_at_once(
    case: str, run: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    fifo, folder = tmp_path / "fifo.json", tmp_path / "folder"
    os.mkfifo(fifo)
    folder.mkdir()
    status, out, err = run(*NOT_REGULAR[case](fifo, folder))
    assert_one_line_error(status, err, "not a regular file (a FIFO, a device or a folder)")
    assert out == ""
    assert {p.name for p in tmp_path.iterdir()} - {"var"} == {"fifo.json", "folder"}
    assert list(folder.iterdir()) == []  # nothing written (simulate's OUT neither)


def _sparse(path: Path, size: int) -> Path:
    with path.open("wb") as sparse:
        sparse.truncate(size)
    return path


def test_a_file_larger_than_the_bound_is_refused_before_a_byte_of_it_is_read(
    run: Callable[..., tuple[int, str, str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(common, "MAX_INPUT_BYTES", 2**20)
    reads = ReadCounting()
    monkeypatch.setattr(common, "os", reads)
    large = _sparse(tmp_path / "large.json", 8 * 2**20)
    for args in (["process", large], ["process", ONETAG, "--gt", large]):
        status, _, err = run(*args)
        assert_one_line_error(status, err, f"{large} (8388608 bytes) is larger than 1048576 bytes")
    assert reads.opened == 2
    assert reads.bytes_read == 0


def test_a_file_growing_past_the_bound_is_read_no_further(
    run: Callable[..., tuple[int, str, str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its size checked says 0 bytes (it grows after the check): read to the bound and a byte."""
    monkeypatch.setattr(common, "MAX_INPUT_BYTES", 2**20)
    reads = ReadCounting(fstat_size=0)
    monkeypatch.setattr(common, "os", reads)
    grown = tmp_path / "grown.json"
    grown.write_bytes(b" " * (3 * 2**20))
    status, _, err = run("process", grown)
    assert_one_line_error(status, err, f"{grown} is larger than 1048576 bytes")
    assert reads.bytes_read == 2**20 + 1


def test_a_gzip_file_is_inflated_no_further_than_the_bound(
    run: Callable[..., tuple[int, str, str]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(common, "MAX_INPUT_BYTES", 2**20)
    pieces: list[int] = []
    real_zlib = common.zlib

    class CountedInflater:
        def __init__(self, **kwargs: Any) -> None:
            self._inflater = real_zlib.decompressobj(**kwargs)

        def __getattr__(self, name: str) -> Any:
            return getattr(self._inflater, name)

        def decompress(self, data: bytes, max_length: int = 0) -> bytes:
            piece: bytes = self._inflater.decompress(data, max_length)
            pieces.append(len(piece))
            return piece

    class CountedZlib:
        def __getattr__(self, name: str) -> Any:
            return getattr(real_zlib, name)

        decompressobj = CountedInflater

    monkeypatch.setattr(common, "zlib", CountedZlib())
    bomb = tmp_path / "bomb.json.gz"
    bomb.write_bytes(gzip.compress(b" " * (64 * 2**20)))
    status, _, err = run("process", bomb)
    assert_one_line_error(status, err, f"{bomb} inflates to more than 1048576 bytes")
    assert sum(pieces) == 2**20 + 1
    zipped = tmp_path / "onetag.json.gz"  # within the bound: read as it is
    zipped.write_bytes(gzip.compress(ONETAG.read_bytes()))
    assert common.read_input_file(zipped) == ONETAG.read_bytes()


def test_a_number_python_does_not_read_is_one_line_error(
    run: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    """Issue 40, finding 1, in the offline commands: a 5,000-digit integer in a session or a
    ground truth."""
    session = tmp_path / "session.json"
    session.write_bytes(ONETAG.read_bytes().rstrip()[:-1] + b', "n": ' + b"7" * 5000 + b"}")
    truth = tmp_path / "truth.json"
    truth.write_bytes(b'{"poses": [' + b"7" * 5000 + b"]}")
    for args, where in (
        (["process", session], f"{session} is not valid JSON: "),
        (["process", ONETAG, "--gt", truth], f"{truth}: not valid JSON: "),
    ):
        status, _, err = run(*args)
        assert_one_line_error(status, err, where, "for integer string conversion")
