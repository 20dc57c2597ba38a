"""``--param`` takes a SLAM parameter within its range only (issue 40's leftovers): a value no
setting means (1e308, NaN, a negative or zero variance) is refused before any work, with exit
status 1 and one line naming the parameter and its range."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_support import assert_one_line_error

from app import cli

ONETAG = Path(__file__).resolve().parents[2] / "data" / "sessions" / "onetag.json"


@pytest.mark.parametrize(
    ("param", "parts"),
    [
        ("huber_k=1e308", ("huber_k", "0 (off) or 0.1 to 100 σ", "1e+308")),
        ("huber_k=NaN", ("huber_k", "finite", "0.1 to 100")),
        ("tag_position_var_m2=-1", ("tag_position_var_m2", "> 0", "1e-12 to 1e+06 m²")),
        ("odom_linear_var_m2_per_s=0", ("odom_linear_var_m2_per_s", "1e-12 to 1e+06")),
        ("max_distance_m=1e308", ("max_distance_m", "0.01 to 1000 m")),
        ("max_iterations=" + "9" * 5000, ("max_iterations", "1 to 10000")),
        ("tag_sizes_m=300:1e308", ("tag_sizes_m[300]", "0.001 to 10 m")),
        ("x" * 5000, ("NAME=VALUE",)),
    ],
    ids=["huge", "nan", "negative", "zero", "distance", "5000-digits", "tag-size", "no-equals"],
)
@pytest.mark.parametrize("command", ["process", "sweep"])
def test_a_param_out_of_range_is_one_line_and_exit_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, param: str, parts: tuple
) -> None:
    argv = [command, str(ONETAG), "--param", param]
    if command == "process":
        argv += ["-o", str(tmp_path / "map.json")]
    status = cli.main(argv)
    line = assert_one_line_error(status, capsys.readouterr().err, *parts)
    assert len(line) < 300, line
    assert not (tmp_path / "map.json").exists()  # refused before any work
