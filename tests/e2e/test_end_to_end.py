"""End to end, as deployed: ``invisible-map serve`` (uvicorn) and ``invisible-map worker`` as
separate processes on a real database, driven over HTTP with the client."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from app.cli.server_process import ServerProcess, WorkerProcess
from app.client import ApiError, Client
from app.domain.frames import rotation_from_quat_xyzw
from app.domain.localize import session_update_documents
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import load_session

pytestmark = [pytest.mark.db, pytest.mark.slow]


def _tag_poses_from_app_map(app_map):
    poses = {}
    for vertex in app_map["tag_vertices"]:
        t, q = vertex["translation"], vertex["rotation"]
        pose = np.eye(4)
        pose[:3, :3] = rotation_from_quat_xyzw(np.array([q["x"], q["y"], q["z"], q["w"]]))
        pose[:3, 3] = [t["x"], t["y"], t["z"]]
        poses[vertex["id"]] = pose
    return poses


def test_upload_is_optimized_by_a_separate_worker(database_url, data_dir, tmp_path):
    path = data_dir / "sessions" / "occam_room.json"
    with (
        ServerProcess(database_url, workers=0, log_path=tmp_path / "api.log") as server,
        WorkerProcess(database_url, log_path=tmp_path / "worker.log"),
        Client(server.url, api_key=server.admin_key) as client,
    ):
        accepted = client.upload_session(path, idempotency_key="e2e-occam")
        assert set(accepted) >= {"session_id", "map_id", "job_id"}
        job = client.wait_for_job(accepted["job_id"], timeout_s=120)
        assert job["state"] == "succeeded"
        assert job["progress"] == 1.0

        again = client.upload_session(path, idempotency_key="e2e-occam")
        assert (again["session_id"], again["map_id"], again["job_id"]) == (
            accepted["session_id"],
            accepted["map_id"],
            accepted["job_id"],
        )
        assert client.list_sessions()["count"] == 1

        served = _tag_poses_from_app_map(client.app_map(accepted["map_id"]))

        route = client.plan_route(accepted["map_id"], {"tag": 0}, {"tag": 5})
        assert route["steps"][-1]["instruction"].startswith("arrive at tag 5")
        kinds = {f["properties"]["kind"] for f in client.geojson(accepted["map_id"])["features"]}
        assert {"node", "tag", "walk"} <= kinds
        navigation = client.start_localization(accepted["map_id"])
        for document in session_update_documents(load_session(path), 50)[:4]:
            estimate = client.update_localization(navigation["id"], **document)
        assert estimate["status"] == "localized"
        assert client.get_localization(navigation["id"])["updates"] == 4

        rebuild = client.rebuild_map(accepted["map_id"], {"tag_position_var_m2": "1e-3"})
        client.wait_for_job(rebuild["job_id"], timeout_s=120)
        versions = client.map_versions(accepted["map_id"])
        assert [v["number"] for v in versions] == [1, 2]
        assert versions[0]["params"]["tag_position_var_m2"] == SlamParams().tag_position_var_m2
        assert versions[1]["params"]["tag_position_var_m2"] == 1e-3
        assert client.get_map(accepted["map_id"])["current_version"]["number"] == 2
        assert client.raw_session(accepted["session_id"]) == path.read_bytes()

    direct = optimize_session(load_session(path), SlamParams()).tag_poses()
    assert sorted(served) == sorted(direct)
    for tag_id, pose in direct.items():
        np.testing.assert_allclose(served[tag_id], pose, atol=1e-9)


def test_embedded_mode_runs_its_own_workers(tmp_path, data_dir):
    database_url = f"sqlite:///{tmp_path / 'embedded.sqlite3'}"  # not migrated: serve migrates
    with (
        ServerProcess(database_url, workers=1, log_path=tmp_path / "serve.log") as server,
        Client(server.url, api_key=server.admin_key) as client,
    ):
        accepted = client.upload_session(data_dir / "sessions" / "onetag.json", compress=True)
        client.wait_for_job(accepted["job_id"], timeout_s=120)
        current = client.get_map(accepted["map_id"])["current_version"]
        assert current["number"] == 1
        info = client.info()
        assert len(info["workers"]) == 1
        with (
            Client(server.url, api_key="im_nope_wrong") as stranger,
            pytest.raises(ApiError) as raised,
        ):
            stranger.info()
        assert raised.value.status_code == 401


def test_serve_with_an_unreachable_database_fails_in_one_line(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "app.cli", "serve", "--port", "1"],
        env={
            "DATABASE_URL": "postgresql+psycopg://nobody@127.0.0.1:1/nothing",
            "PATH": "/usr/bin:/bin",
        },
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("invisible-map: error: cannot use the database")
