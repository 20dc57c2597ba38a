"""What the real app downloads and shows (issue 14): the map's picture (PUT on the session, GET on
the map, cacheable), its display name (derived from map_id, editable by an admin), and the app-map
(the same document as ``invisible-map process --app-map``, gzip, an ETag that follows the export).
Every failure path; SQLite and PostgreSQL."""

from __future__ import annotations

import gzip
import hashlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from api_support import ADMIN, ONETAG, Api, running_api

from app.cli import program
from app.config import Settings
from app.domain.formats.app_model import check_app_map
from app.storage.images import MAX_IMAGE_BYTES
from app.storage.orm import SessionImage
from workers.main import Worker
from workers.pipeline import BUILD_MAP_STAGES

pytestmark = pytest.mark.db

JPEG = b"\xff\xd8\xff\xe0\x00\x10JFIF\x00" + bytes(range(256)) * 4 + b"\xff\xd9"
OTHER_JPEG = b"\xff\xd8\xff\xdb" + b"\x01" * 500 + b"\xff\xd9"
JPEG_HEADERS = {"Content-Type": "image/jpeg"}


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def upload(api: Api, *, map_id: str = "Lab 1700000000", auth: dict[str, str] | None = None):
    document = json.loads(ONETAG.read_bytes())
    document["map_id"] = map_id
    return api.uploaded(json.dumps(document).encode(), auth=auth)


def put_image(api: Api, session_id: int, body: bytes, auth: dict[str, str], **headers: str):
    return api.client.put(
        f"/v1/sessions/{session_id}/image",
        content=body,
        headers={**JPEG_HEADERS, **auth, **headers},
    )


def run_worker_once(api: Api) -> None:
    settings = Settings(
        database_url=api.settings.database_url, lease_s=30.0, poll_s=0.05, retry_backoff_s=0.0
    )
    assert Worker(api.db, settings, pipelines={"build_map": BUILD_MAP_STAGES}).run_once()


# --------------------------------------------------------------------------- the picture


def test_the_picture_is_stored_idempotently_listed_and_served_cacheable(api: Api) -> None:
    device = api.device()
    created = upload(api, auth=device)
    maps_url = f"/v1/maps/{created['map_id']}"
    listed = api.client.get("/v1/maps", headers=device).json()["data"][0]
    assert listed["image_url"] is None

    first = put_image(api, created["session_id"], JPEG, device)
    assert first.status_code == 200, first.text
    body = first.json()
    assert body["changed"] is True
    assert body["sha256"] == hashlib.sha256(JPEG).hexdigest()
    assert body["size_bytes"] == len(JPEG)
    assert body["image_url"] == f"{maps_url}/image?v={body['sha256'][:16]}"
    again = put_image(api, created["session_id"], JPEG, device).json()
    assert again == {**body, "changed": False}
    assert api.count(SessionImage) == 1

    listed = api.client.get("/v1/maps", headers=device).json()["data"][0]
    assert listed["image_url"] == body["image_url"]
    assert api.client.get(maps_url, headers=ADMIN).json()["image_url"] == body["image_url"]
    served = api.client.get(body["image_url"], headers=device)
    assert served.status_code == 200
    assert served.content == JPEG
    assert served.headers["Content-Type"] == "image/jpeg"
    assert served.headers["Cache-Control"] == "private, max-age=31536000, immutable"
    unversioned = api.client.get(f"{maps_url}/image", headers=device)
    assert unversioned.headers["Cache-Control"] == "private, no-cache"
    stale = api.client.get(f"{maps_url}/image?v=0000000000000000", headers=device)
    assert stale.headers["Cache-Control"] == "private, no-cache"
    assert stale.content == JPEG
    cached = api.client.get(
        f"{maps_url}/image", headers={**device, "If-None-Match": served.headers["ETag"]}
    )
    assert cached.status_code == 304

    replaced = put_image(api, created["session_id"], OTHER_JPEG, device).json()
    assert replaced["changed"] is True
    assert replaced["image_url"] != body["image_url"]
    assert api.client.get(f"{maps_url}/image", headers=device).content == OTHER_JPEG
    assert api.count(SessionImage) == 1


@pytest.mark.parametrize(
    ("body", "headers", "status", "code", "field"),
    [
        (JPEG, {"Content-Type": "image/png"}, 415, "unsupported_media_type", "Content-Type"),
        (JPEG, {"Content-Type": "application/json"}, 415, "unsupported_media_type", None),
        (JPEG, {"Content-Encoding": "gzip"}, 415, "unsupported_media_type", "Content-Encoding"),
        (b"", {}, 422, "invalid_image", "body"),
        (b"\x89PNG\r\n\x1a\n" + b"\x00" * 100, {}, 422, "invalid_image", "body"),
        (JPEG[:-2], {}, 422, "invalid_image", "body"),
        (b"\xff\xd8\xff" + b"\x00" * MAX_IMAGE_BYTES, {}, 413, "payload_too_large", None),
    ],
    ids=["png", "json", "gzip", "empty", "not-jpeg", "cut-short", "too-large"],
)
def test_a_picture_that_is_not_an_acceptable_jpeg_is_refused_and_nothing_stored(
    api: Api, body: bytes, headers: dict[str, str], status: int, code: str, field: str | None
) -> None:
    created = upload(api)
    response = api.client.put(
        f"/v1/sessions/{created['session_id']}/image",
        content=body,
        headers={**JPEG_HEADERS, **ADMIN, **headers},
    )
    assert response.status_code == status, response.text
    assert response.json()["code"] == code
    if field is not None:
        assert response.json()["field"] == field
    assert api.count(SessionImage) == 0


def test_only_the_uploader_or_an_admin_may_set_a_picture(api: Api) -> None:
    owner, stranger = api.device(), api.device()
    created = upload(api, auth=owner)
    url = f"/v1/sessions/{created['session_id']}/image"
    assert put_image(api, created["session_id"], JPEG, stranger).status_code == 404
    no_key = api.client.put(url, content=JPEG, headers=JPEG_HEADERS)
    assert no_key.status_code == 401
    assert put_image(api, 999_999, JPEG, ADMIN).status_code == 404
    assert put_image(api, created["session_id"], JPEG, ADMIN).status_code == 200


def test_a_map_without_a_picture_or_no_such_map_is_a_404(api: Api) -> None:
    created = upload(api)
    response = api.client.get(f"/v1/maps/{created['map_id']}/image", headers=ADMIN)
    assert response.status_code == 404
    assert response.json()["code"] == "no_image"
    assert api.client.get("/v1/maps/999999/image", headers=ADMIN).status_code == 404
    assert api.client.get(f"/v1/maps/{created['map_id']}/image").status_code == 401


# --------------------------------------------------------------------------- the display name


def test_the_display_name_is_the_typed_name_and_an_admin_can_change_it(api: Api) -> None:
    created = upload(api, map_id="Lab 1700000000")
    url = f"/v1/maps/{created['map_id']}"
    shown = api.client.get(url, headers=ADMIN).json()
    assert (shown["name"], shown["display_name"]) == ("Lab 1700000000", "Lab")

    renamed = api.client.patch(url, json={"display_name": "  Occam lab  "}, headers=ADMIN)

    assert renamed.status_code == 200, renamed.text
    assert renamed.json()["display_name"] == "Occam lab"
    assert renamed.json()["name"] == "Lab 1700000000"  # the upload's map_id never changes
    listed = api.client.get("/v1/maps", headers=api.device()).json()["data"][0]
    assert listed["display_name"] == "Occam lab"


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"display_name": "   "}, "display_name"),
        ({"display_name": ""}, "display_name"),
        ({"display_name": "x" * 201}, "display_name"),
        ({"display_name": 3}, "display_name"),
        ({}, "display_name"),
        ({"display_name": "A", "name": "B"}, "name"),
    ],
)
def test_a_bad_display_name_is_a_422_naming_the_field(
    api: Api, body: dict[str, Any], field: str
) -> None:
    created = upload(api)
    response = api.client.patch(f"/v1/maps/{created['map_id']}", json=body, headers=ADMIN)
    assert response.status_code == 422, response.text
    assert response.json()["field"] == field
    shown = api.client.get(f"/v1/maps/{created['map_id']}", headers=ADMIN).json()
    assert shown["display_name"] == "Lab"


def test_only_an_admin_may_rename_a_map_that_exists(api: Api) -> None:
    created = upload(api)
    url = f"/v1/maps/{created['map_id']}"
    by_device = api.client.patch(url, json={"display_name": "X"}, headers=api.device())
    assert by_device.status_code == 403
    assert api.client.patch(url, json={"display_name": "X"}).status_code == 401
    missing = api.client.patch("/v1/maps/999999", json={"display_name": "X"}, headers=ADMIN)
    assert missing.status_code == 404


# --------------------------------------------------------------------------- the app-map


def test_the_served_app_map_is_the_clis_document_gzip_and_routable(
    api: Api, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    created = upload(api)
    run_worker_once(api)
    url = f"/v1/maps/{created['map_id']}/app-map"

    plain = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "identity"})
    assert plain.status_code == 200
    assert "Content-Encoding" not in plain.headers
    session_file = tmp_path / "lab.json"
    document = json.loads(ONETAG.read_bytes())
    document["map_id"] = "Lab 1700000000"
    session_file.write_text(json.dumps(document))
    written = tmp_path / "lab.app-map.json"
    assert program.main(["process", str(session_file), "--app-map", str(written)]) == 0
    assert json.loads(written.read_text()) == plain.json()
    assert check_app_map(plain.json()).ok

    with api.client.stream("GET", url, headers={**ADMIN, "Accept-Encoding": "gzip"}) as compressed:
        assert compressed.headers["Content-Encoding"] == "gzip"
        raw = b"".join(compressed.iter_raw())
    assert gzip.decompress(raw) == plain.content

    etag = plain.headers["ETag"]
    assert api.client.get(url, headers={**ADMIN, "If-None-Match": etag}).status_code == 304
    # a new export makes the phone download the file again
    monkeypatch.setattr("app.api.routes.maps.APP_MAP_EXPORT", 999)
    assert api.client.get(url, headers={**ADMIN, "If-None-Match": etag}).status_code == 200
