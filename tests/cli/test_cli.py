"""The ``invisible-map`` command, run as a user runs it: real subprocesses and ``main([...])``.

Every failure on bad input must be one line on stderr, ``invisible-map: error: …``, exit status 1,
and no traceback; argparse misuse exits 2.
"""

from __future__ import annotations

import gzip
import json
import math
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_support import assert_one_line_error

from app import cli
from app.domain.formats.app_model import check_app_map
from app.domain.mapping.params import SlamParams

REPO_ROOT = Path(__file__).resolve().parents[2]
DATA_DIR = REPO_ROOT / "data"
SESSIONS_DIR = DATA_DIR / "sessions"
GROUND_TRUTH_DIR = DATA_DIR / "ground_truth"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

DEMO_SESSIONS = [
    "occam_room",
    "floor_2_straight",
    "straight_209_occam",
    "desnat_straight_once",
    "pgt_tester3",
    "singletag3times",
    "onetag",
]
EVALUATION_KEYS = {
    "dataset",
    "poses",
    "tags",
    "detections_used",
    "detections_rejected",
    "optimize_ms",
    "gt_metric_pre",
    "gt_metric_opt",
    "tag_rmse_pre_m",
    "tag_rmse_opt_m",
    "shift_pre",
    "shift_opt",
}
#: (poses, tag detections) of the sessions evaluated against mac_1_2 (data/README.md).
MAC_SESSIONS = {
    "floor_2_straight": (1004, 54),
    "straight_209_occam": (1007, 150),
    "desnat_straight_once": (604, 79),
}


# --------------------------------------------------------------------------- helpers


def run_cli(*args: Any, command: list[str] | None = None) -> subprocess.CompletedProcess[str]:
    """Run the command in a fresh interpreter from the repository root."""
    command = command or [sys.executable, "-m", "app.cli"]
    return subprocess.run(
        [*command, *(str(a) for a in args)],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )


def console_script() -> str | None:
    """The installed ``invisible-map`` entry point, if there is one."""
    beside_python = Path(sys.executable).parent / "invisible-map"
    if beside_python.is_file():
        return str(beside_python)
    return shutil.which("invisible-map")


def onetag_document() -> dict[str, Any]:
    return json.loads((SESSIONS_DIR / "onetag.json").read_text())


def write_json(path: Path, document: Any) -> Path:
    path.write_text(json.dumps(document))
    return path


def phone_T_poi_row_major() -> list[float]:
    return [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, 1.0]


def metric_values(stdout: str, label: str) -> tuple[float, float]:
    """The ``pre`` and ``opt`` numbers of the ``label: pre X  opt Y`` line."""
    match = re.search(rf"^{label}: pre ([0-9.]+)(?: m)?\s+opt ([0-9.]+)", stdout, re.MULTILINE)
    assert match, stdout
    return float(match.group(1)), float(match.group(2))


# --------------------------------------------------------------------------- process


@pytest.fixture(scope="module")
def occam_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("occam")
    paths = {"map": out / "occam.map.json", "app": out / "occam.app.json", "png": out / "o.png"}
    proc = run_cli(
        "process",
        SESSIONS_DIR / "occam_room.json",
        "--gt",
        GROUND_TRUTH_DIR / "occam_room_tape.json",
        "-o",
        paths["map"],
        "--app-map",
        paths["app"],
        "--plot",
        paths["png"],
    )
    return proc, paths


@pytest.mark.slow
def test_process_occam_room_succeeds_and_writes_files(occam_run):
    proc, paths = occam_run
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    for path in paths.values():
        assert path.is_file()
        assert path.stat().st_size > 0
        assert f"wrote {path}" in proc.stdout
    # Writes are atomic: no temporary file is left behind.
    assert sorted(p.name for p in paths["map"].parent.iterdir()) == sorted(
        p.name for p in paths.values()
    )


@pytest.mark.slow
def test_process_writes_our_map_format(occam_run):
    _, paths = occam_run
    document = json.loads(paths["map"].read_text())
    assert document["format"] == "invisible-map/map"
    assert len(document["tags"]) == 8
    assert sorted(tag["id"] for tag in document["tags"]) == list(range(8))
    assert len(document["trajectory"]["pose_id"]) == 621
    for tag in document["tags"]:
        assert len(tag["pose"]) == 7
        assert all(math.isfinite(v) for v in tag["pose"])


@pytest.mark.slow
def test_process_writes_the_app_download_format(occam_run):
    _, paths = occam_run
    document = json.loads(paths["app"].read_text())
    assert {"tag_vertices", "odometry_vertices", "waypoints_vertices"} <= set(document)
    assert len(document["tag_vertices"]) == 8
    vertices = document["odometry_vertices"]
    # every pose, then the path graph's junctions (numbered after the last pose)
    assert len(vertices) > 621
    for vertex in vertices:
        assert {"poseId", "translation", "rotation", "adjChi2", "vizTags", "neighbors"} <= set(
            vertex
        )
        assert set(vertex["translation"]) == {"x", "y", "z"}
        assert set(vertex["rotation"]) == {"x", "y", "z", "w"}
        norm = math.sqrt(sum(v * v for v in vertex["rotation"].values()))
        assert norm == pytest.approx(1.0, abs=1e-6)
        assert all(isinstance(n, int) for n in vertex["neighbors"])
    assert [v["poseId"] for v in vertices[:621]] == list(range(621))
    assert all(v["poseId"] > 620 for v in vertices[621:])
    assert check_app_map(document).ok  # the app can route on it
    # Tags are seen from some poses: their vizTags add up to the detections used.
    assert sum(v["vizTags"] for v in vertices) > 0
    assert document["waypoints_vertices"] == []


@pytest.mark.slow
def test_process_writes_a_png(occam_run):
    _, paths = occam_run
    assert paths["png"].read_bytes()[:8] == PNG_MAGIC


@pytest.mark.slow
def test_process_reports_the_ground_truth_metric(occam_run):
    proc, _ = occam_run
    pre, opt = metric_values(proc.stdout, "ground-truth metric")
    # data/README.md: the pre-optimized occam_room map scores 0.0553 (all 8 tags are in the map).
    assert pre == pytest.approx(0.0553, abs=1e-3)
    assert 0 < opt < 1
    assert "(8 tags with ground truth)" in proc.stdout
    rmse_pre, rmse_opt = metric_values(proc.stdout, "tag RMSE")
    assert 0 < rmse_pre < 1
    assert 0 < rmse_opt < 1
    assert re.search(r"^shift metric: pre [0-9.]+\s+opt [0-9.]+$", proc.stdout, re.MULTILINE)
    assert proc.stdout.startswith("duncan-occam-room")
    assert "621 poses" in proc.stdout


def test_process_in_process_single_detection(tmp_path, capsys):
    out = tmp_path / "onetag.map.json"
    assert cli.main(["process", str(SESSIONS_DIR / "onetag.json"), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    assert "map: 1 tags, 1 detections used" in captured.out
    document = json.loads(out.read_text())
    assert [tag["id"] for tag in document["tags"]] == [306]
    assert len(document["trajectory"]["pose_id"]) == 25


def test_process_without_ground_truth_prints_no_ground_truth_metric(capsys):
    assert cli.main(["process", str(SESSIONS_DIR / "pgt_tester3.json")]) == 0
    out = capsys.readouterr().out
    assert "shift metric:" in out
    assert "ground-truth metric" not in out


@pytest.mark.slow
def test_process_session_without_detections_says_no_map_can_be_made(tmp_path):
    document = onetag_document()
    document["tag_data"] = []
    session = write_json(tmp_path / "notags.json", document)
    app_map = tmp_path / "notags.app.json"

    proc = run_cli("process", session, "--app-map", app_map)

    assert proc.returncode != 0
    assert "no tags were recorded: a map needs at least one tag" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not app_map.exists()


@pytest.mark.slow
def test_process_single_detection_session_as_subprocess(tmp_path):
    out = tmp_path / "m.json"
    proc = run_cli("process", SESSIONS_DIR / "onetag.json", "-o", out)
    assert proc.returncode == 0, proc.stderr
    assert "1 detections of 1 tags" in proc.stdout
    assert json.loads(out.read_text())["tags"][0]["id"] == 306


def test_process_reads_gzipped_session(tmp_path, capsys):
    path = tmp_path / "onetag.json.gz"
    path.write_bytes(gzip.compress((SESSIONS_DIR / "onetag.json").read_bytes()))
    assert cli.main(["process", str(path)]) == 0
    assert "25 poses" in capsys.readouterr().out


def test_process_poi_off_by_one_and_no_poi_correction(tmp_path, capsys):
    document = onetag_document()
    document["location_data"] = [
        {"name": "door", "pose_id": 0, "timestamp": 0.0, "transform": phone_T_poi_row_major()}
    ]
    session = write_json(tmp_path / "poi.json", document)
    app_map = tmp_path / "poi.app.json"

    # The app's pose_id 0 means pose −1 after the correction: there is no such pose.
    assert cli.main(["process", str(session), "--app-map", str(app_map)]) == 1
    assert_one_line_error(1, capsys.readouterr().err, "location_data[0].pose_id")
    assert not app_map.exists()

    args = ["process", str(session), "--app-map", str(app_map), "--no-poi-correction"]
    assert cli.main(args) == 0
    capsys.readouterr()
    waypoints = json.loads(app_map.read_text())["waypoints_vertices"]
    assert [w["id"] for w in waypoints] == ["door"]


def test_process_poi_becomes_a_waypoint(tmp_path, capsys):
    document = onetag_document()
    document["location_data"] = [
        {"name": "stairs", "pose_id": 5, "timestamp": 0.0, "transform": phone_T_poi_row_major()}
    ]
    session = write_json(tmp_path / "poi.json", document)
    app_map = tmp_path / "poi.app.json"
    assert cli.main(["process", str(session), "--app-map", str(app_map)]) == 0
    capsys.readouterr()
    waypoints = json.loads(app_map.read_text())["waypoints_vertices"]
    assert [w["id"] for w in waypoints] == ["stairs"]
    assert set(waypoints[0]["translation"]) == {"x", "y", "z"}


def test_process_param_changes_the_map(tmp_path, capsys):
    default_out, tuned_out = tmp_path / "default.json", tmp_path / "tuned.json"
    session = str(SESSIONS_DIR / "pgt_tester3.json")
    assert cli.main(["process", session, "-o", str(default_out)]) == 0
    args = ["process", session, "-o", str(tuned_out), "--param", "tag_position_var_m2=1e-2"]
    assert cli.main([*args, "--param", "compute_marginals=false"]) == 0
    capsys.readouterr()
    default, tuned = json.loads(default_out.read_text()), json.loads(tuned_out.read_text())
    assert default["params"]["tag_position_var_m2"] == SlamParams().tag_position_var_m2
    assert tuned["params"]["tag_position_var_m2"] == pytest.approx(1e-2)
    assert tuned["params"]["compute_marginals"] is False


# --------------------------------------------------------------------------- errors


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _truncated(d: Path) -> Path:
    raw = (SESSIONS_DIR / "occam_room.json").read_bytes()
    path = d / "truncated.json"
    path.write_bytes(raw[: len(raw) // 2])
    return path


def _with_nan(d: Path) -> Path:
    document = onetag_document()
    document["pose_data"][3]["pose"][5] = math.nan
    return write_json(d / "nan.json", document)  # json.dumps writes the token NaN


def _huge_pose_id(d: Path) -> Path:
    document = onetag_document()
    document["pose_data"][24]["id"] = 10**30
    return write_json(d / "huge_id.json", document)


ONETAG = SESSIONS_DIR / "onetag.json"
#: name: (arguments given a scratch folder, parts the one-line message must contain)
ERROR_CASES: dict[str, tuple[Callable[[Path], list[Any]], tuple[str, ...]]] = {
    "missing session": (lambda d: ["process", d / "missing.json"], ("missing.json",)),
    "non-JSON session": (
        lambda d: ["process", _write(d / "bad.json", "this is not json")],
        ("bad.json", "not valid JSON"),
    ),
    "truncated session": (lambda d: ["process", _truncated(d)], ("not valid JSON",)),
    "NaN in session": (lambda d: ["process", _with_nan(d)], ("pose_data[3].pose[5]", "non-finite")),
    "session is a directory": (lambda d: ["process", d], ()),
    "malformed RTAB-Map ground truth": (
        lambda d: ["process", ONETAG, "--gt", _write(d / "gt.txt", "rpy 1 2 x\n")],
        ("gt.txt",),
    ),
    "malformed JSON ground truth": (
        lambda d: ["process", ONETAG, "--gt", _write(d / "gt.json", '{"poses": 3}')],
        ("gt.json",),
    ),
    "missing ground truth": (
        lambda d: ["evaluate", ONETAG, "--gt", d / "nogt.txt"],
        ("nogt.txt",),
    ),
    "unknown param": (
        lambda _: ["process", ONETAG, "--param", "nonsense=1"],
        ("nonsense", "tag_position_var_m2"),
    ),
    "negative variance": (
        lambda _: ["process", ONETAG, "--param", "tag_position_var_m2=-1"],
        ("tag_position_var_m2", "> 0"),
    ),
    "param without value": (
        lambda _: ["process", ONETAG, "--param", "novalue"],
        ("NAME=VALUE", "novalue"),
    ),
    "non-numeric param": (
        lambda _: [
            "evaluate",
            ONETAG,
            "--gt",
            GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt",
            "--param",
            "huber_k=big",
        ],
        ("huber_k", "big"),
    ),
    "two gt for three sessions": (
        lambda _: [
            "evaluate",
            ONETAG,
            ONETAG,
            ONETAG,
            "--gt",
            GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt",
            "--gt",
            GROUND_TRUTH_DIR / "rtabmap_wh_4.txt",
        ],
        ("2", "3 sessions"),
    ),
    "output folder missing": (
        lambda d: ["process", ONETAG, "-o", d / "no" / "such" / "dir" / "map.json"],
        ("no/such/dir",),
    ),
    "infinite tag size": (
        lambda d: ["process", ONETAG, "--param", "tag_sizes_m=306:inf", "-o", d / "m.json"],
        ("tag_sizes_m",),
    ),
    "pose id beyond int64": (lambda d: ["process", _huge_pose_id(d)], ("pose_data[24].id",)),
}


@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_error_is_one_line_in_process(case, tmp_path, capsys):
    make_args, parts = ERROR_CASES[case]
    code = cli.main([str(a) for a in make_args(tmp_path)])
    captured = capsys.readouterr()
    assert_one_line_error(code, captured.err, *parts)
    assert captured.out == ""


@pytest.mark.slow
@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_error_is_one_line_in_a_subprocess(case, tmp_path):
    make_args, parts = ERROR_CASES[case]
    proc = run_cli(*make_args(tmp_path))
    assert_one_line_error(proc.returncode, proc.stderr, *parts)
    assert proc.stdout == ""


@pytest.mark.slow
def test_no_subcommand_exits_2():
    proc = run_cli()
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "usage: invisible-map" in proc.stderr


@pytest.mark.parametrize(
    "argv",
    [[], ["frobnicate"], ["process"], ["evaluate", str(ONETAG)], ["process", str(ONETAG), "-x"]],
)
def test_command_line_misuse_exits_2(argv, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2
    assert "usage:" in capsys.readouterr().err


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for command in ("process", "evaluate", "evaluate-samples"):
        assert command in out


#: What building the command's parser must not import (issue 28, finding 10: `process --help`
#: took 0.44 s, all of it importing them): each command imports what it needs when it runs.
NOT_FOR_THE_PARSER = (
    "fastapi", "starlette", "uvicorn", "sqlalchemy", "alembic", "psycopg", "pydantic",
    "matplotlib", "numpy", "gtsam", "networkx", "optuna", "tqdm", "asyncio",
)  # fmt: skip


def test_the_parser_imports_no_heavy_library():
    probe = (
        "import sys\n"
        "from app.cli import program\n"
        "parser = program._parser()\n"
        "for argv in (['process', 'x.json'], ['serve'], ['sweep', 'x'], ['import', 'a.zip']):\n"
        "    parser.parse_args(argv)\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {NOT_FOR_THE_PARSER!r}))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO_ROOT, capture_output=True, text=True, check=True
    )
    assert proc.stdout.strip() == "[]", proc.stdout


def test_help_is_printed_without_importing_the_core():
    proc = run_cli(
        "process", "--help", command=[sys.executable, "-X", "importtime", "-m", "app.cli"]
    )
    assert proc.returncode == 0, proc.stderr
    assert "--app-map" in proc.stdout
    imported = {line.rsplit("|", 1)[-1].strip() for line in proc.stderr.splitlines()}
    assert not {name for name in imported if name.split(".")[0] in NOT_FOR_THE_PARSER}


def test_process_imports_the_mapping_core_only():
    """``process`` needs numpy and gtsam; the web stack, the database, plotting (without
    ``--plot``) and the path graph (without ``-o`` or ``--app-map``) it does not import."""
    probe = (
        "import sys\n"
        "from app.cli import program\n"
        f"assert program.main(['process', {str(ONETAG)!r}]) == 0\n"
        "heavy = ('fastapi', 'sqlalchemy', 'matplotlib', 'networkx', 'gtsam')\n"
        "print(sorted(m for m in heavy if m in sys.modules))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO_ROOT, capture_output=True, text=True, check=True
    )
    assert proc.stdout.splitlines()[-1] == "['gtsam']", proc.stdout


# --------------------------------------------------------------------------- console script


@pytest.mark.slow
def test_installed_console_script(tmp_path):
    script = console_script()
    if script is None:
        pytest.skip("the invisible-map console script is not installed")
    out = tmp_path / "m.json"
    proc = run_cli("process", ONETAG, "-o", out, command=[script])
    assert proc.returncode == 0, proc.stderr
    assert json.loads(out.read_text())["format"] == "invisible-map/map"

    proc = run_cli("process", tmp_path / "missing.json", command=[script])
    assert_one_line_error(proc.returncode, proc.stderr, "missing.json")

    proc = run_cli(command=[script])
    assert proc.returncode == 2


# --------------------------------------------------------------------------- evaluate

MAC_ARGS = [SESSIONS_DIR / f"{name}.json" for name in MAC_SESSIONS]


@pytest.fixture(scope="module")
def evaluate_rtabmap():
    proc = run_cli(
        "evaluate", *MAC_ARGS, "--gt", GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt", "--json"
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.fixture(scope="module")
def evaluate_gt_json():
    gt = GROUND_TRUTH_DIR / "mac_1_2_yup_reference.json"
    proc = run_cli("evaluate", *MAC_ARGS, "--gt", gt, "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.slow
def test_evaluate_json_rows(evaluate_rtabmap):
    rows = evaluate_rtabmap
    assert isinstance(rows, list)
    assert [row["dataset"] for row in rows] == list(MAC_SESSIONS)
    for row in rows:
        assert set(row) >= EVALUATION_KEYS
        poses, detections = MAC_SESSIONS[row["dataset"]]
        assert row["poses"] == poses
        assert row["detections_used"] + row["detections_rejected"] == detections
        assert row["detections_used"] > 0
        assert row["tags"] > 0
        assert row["optimize_ms"] > 0
        for key in ("gt_metric_pre", "gt_metric_opt", "tag_rmse_pre_m", "tag_rmse_opt_m"):
            assert isinstance(row[key], float)
            assert 0 < row[key] < 10
    assert [row["poses"] for row in rows] == [1004, 1007, 604]


@pytest.mark.slow
@pytest.mark.parametrize("dataset", ["floor_2_straight", "straight_209_occam"])
def test_evaluate_optimized_beats_pre_optimized(evaluate_rtabmap, dataset):
    row = next(r for r in evaluate_rtabmap if r["dataset"] == dataset)
    assert row["gt_metric_opt"] < row["gt_metric_pre"]


@pytest.mark.slow
def test_evaluate_both_ground_truth_forms_agree(evaluate_rtabmap, evaluate_gt_json):
    assert [r["dataset"] for r in evaluate_gt_json] == [r["dataset"] for r in evaluate_rtabmap]
    for from_text, from_json in zip(evaluate_rtabmap, evaluate_gt_json, strict=True):
        for key in ("gt_metric_pre", "gt_metric_opt", "tag_rmse_pre_m", "tag_rmse_opt_m"):
            assert from_json[key] == pytest.approx(from_text[key], abs=1e-6), key
        assert from_json["poses"] == from_text["poses"]
        assert from_json["tags"] == from_text["tags"]


def test_evaluate_table_output(capsys):
    argv = ["evaluate", *map(str, MAC_ARGS), "--gt", str(GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt")]
    assert cli.main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    header = [line for line in lines if "GT pre" in line]
    assert len(header) == 1
    assert header[0].startswith("|")
    assert "GT opt" in header[0]
    assert "shift opt" in header[0]
    for name in MAC_SESSIONS:
        row = next(line for line in lines if line.startswith(f"| {name} "))
        assert "—" not in row.split("|")[7]  # the GT pre column has a number
    # The table's columns line up.
    table = [line for line in lines if line.startswith("|")]
    assert len(table) == 2 + len(MAC_SESSIONS)
    assert len({len(line) for line in table}) == 1


def test_evaluate_one_gt_per_session(capsys):
    rtabmap = str(GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt")
    reference = str(GROUND_TRUTH_DIR / "mac_1_2_yup_reference.json")
    sessions = [str(SESSIONS_DIR / "desnat_straight_once.json"), str(ONETAG)]
    argv = ["evaluate", *sessions, "--gt", rtabmap, "--gt", reference, "--json"]
    assert cli.main(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [row["dataset"] for row in rows] == ["desnat_straight_once", "onetag"]
    assert rows[0]["gt_metric_pre"] is not None
    # onetag's one tag (306) cannot be scored against ground truth: the metric needs two tags.
    assert rows[1]["gt_metric_opt"] is None


@pytest.mark.slow
def test_evaluate_joint_json_as_issue_15_pins_it(capsys):
    """``evaluate A B C --gt GT --joint --json``: one row per session alone, then the joint row
    with the usual fields and ``by_session``."""
    argv = ["evaluate", *map(str, MAC_ARGS), "--gt", str(GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt")]
    assert cli.main([*argv, "--joint", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [row["dataset"] for row in rows] == [*MAC_SESSIONS, "joint"]
    joint = rows[-1]
    assert set(joint) >= EVALUATION_KEYS | {"by_session"}
    assert joint["poses"] == sum(poses for poses, _ in MAC_SESSIONS.values())
    assert set(joint["by_session"]) == set(MAC_SESSIONS)
    for name, row in joint["by_session"].items():
        alone = next(r for r in rows if r["dataset"] == name)
        # on all the walk's tags (issue 25: not only those that placed it)
        assert row["tags_compared"] == alone["tags_with_ground_truth"]
        assert row["gt_metric_alone"] == pytest.approx(alone["gt_metric_opt"], rel=1e-9)
        assert row["tag_rmse_alone_m"] == pytest.approx(alone["tag_rmse_opt_m"], rel=1e-9)
        # issue 25's target: no walk's own tags more than 5% worse than alone
        assert row["gt_metric_joint"] <= 1.05 * row["gt_metric_alone"], name
        assert row["tag_rmse_joint_m"] <= 1.05 * row["tag_rmse_alone_m"], name
        shared, own = row["shared"], row["own"]
        assert shared["tags_compared"] + own["tags_compared"] >= row["tags_compared"]
        assert set(shared["tags"]).isdisjoint(own["tags"])
        assert row["weighting"]
    assert joint["by_session"]["desnat_straight_once"]["disagreement_factor"] > 1
    # the rows alone are what evaluate prints without --joint (but for the timings)
    assert cli.main([*argv, "--json"]) == 0
    untimed = [{k: v for k, v in r.items() if k != "optimize_ms"} for r in rows[:-1]]
    again = json.loads(capsys.readouterr().out)
    assert [{k: v for k, v in r.items() if k != "optimize_ms"} for r in again] == untimed


def test_evaluate_joint_table_and_its_errors(capsys):
    desnat, straight = SESSIONS_DIR / "desnat_straight_once.json", MAC_ARGS[1]
    rtabmap = str(GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt")
    assert cli.main(["evaluate", str(desnat), str(straight), "--gt", rtabmap, "--joint"]) == 0
    out = capsys.readouterr().out
    assert "| joint " in out
    assert "RMSE shared m" in out
    assert "RMSE own m" in out
    assert "weighed by its own noise" in out or "down-weighted" in out
    reference = str(GROUND_TRUTH_DIR / "mac_1_2_yup_reference.json")
    proc = run_cli("evaluate", desnat, straight, "--gt", rtabmap, "--gt", reference, "--joint")
    assert_one_line_error(proc.returncode, proc.stderr, "--joint", "one --gt")
    proc = run_cli("evaluate", desnat, ONETAG, "--gt", rtabmap, "--joint")
    assert_one_line_error(proc.returncode, proc.stderr, "'onetag'", "too_few_shared_tags")


# --------------------------------------------------------------------------- demo


@pytest.mark.slow
def test_demo_writes_maps_plots_and_table(tmp_path):
    out = tmp_path / "demo"
    proc = run_cli("evaluate-samples", "--out", out)

    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    table = (out / "evaluation.md").read_text()
    assert "GT pre" in table
    for name in DEMO_SESSIONS:
        assert f"| {name} " in table
        assert (out / f"{name}.png").read_bytes()[:8] == PNG_MAGIC
        document = json.loads((out / f"{name}.map.json").read_text())
        assert document["format"] == "invisible-map/map"
        app_map = json.loads((out / f"{name}.app-map.json").read_text())
        assert {"tag_vertices", "odometry_vertices", "waypoints_vertices"} <= set(app_map)
    assert len(list(out.glob("*.png"))) == len(DEMO_SESSIONS)
    assert str(out) in proc.stdout
    assert "GT pre" in proc.stdout
