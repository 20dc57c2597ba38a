"""``parse_update`` checks and orthonormalizes an update's poses all at once; it must give, bit
for bit, what checking them one by one with ``rigid_pose`` gives, and the same first error."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.domain.errors import SessionFormatError
from app.domain.localize import (
    MAX_UPDATE_DETECTIONS,
    MAX_UPDATE_POSES,
    LocalizationUpdateError,
    parse_update,
    session_update_documents,
)
from app.domain.upload.fields import rigid_pose
from app.domain.upload.session import load_session

WALK = Path(__file__).resolve().parents[2] / "data" / "sessions" / "desnat_straight_once.json"


def one_by_one(document: dict[str, Any]) -> np.ndarray:
    """The poses as the parser checked them before: ``rigid_pose`` on each in turn."""
    try:
        return np.stack(
            [
                rigid_pose(
                    np.asarray(entry["pose"], dtype=np.float64).reshape(4, 4).T,
                    f"poses[{i}].pose",
                )
                for i, entry in enumerate(document["poses"])
            ]
        )
    except SessionFormatError as err:
        raise LocalizationUpdateError(err.field, err.reason) from err


@pytest.fixture(scope="module")
def documents() -> list[dict[str, Any]]:
    return session_update_documents(load_session(WALK), 20)


def test_the_poses_are_bit_for_bit_those_checked_one_by_one(documents):
    for document in documents:
        assert np.array_equal(parse_update(document).session_T_phone, one_by_one(document))


def _rotated(pose: list[float], degrees: float) -> list[float]:
    """``pose`` (column-major) with a slightly non-orthonormal rotation block."""
    changed = list(pose)
    changed[0] *= 1.0 + np.radians(degrees)
    return changed


@pytest.mark.parametrize(
    ("change", "field", "reason"),
    [
        (lambda d: d["poses"][2]["pose"].__setitem__(0, 3.0), "poses[2].pose", "orthonormal"),
        (lambda d: d["poses"][1]["pose"].__setitem__(3, 0.5), "poses[1].pose", "last row"),
        (lambda d: d["poses"][3]["pose"].__setitem__(12, 1e6), "poses[3].pose", "beyond"),
        (
            lambda d: d["poses"][2].__setitem__(
                "pose", [-v for v in d["poses"][2]["pose"][:12]] + d["poses"][2]["pose"][12:]
            ),
            "poses[2].pose",
            "",
        ),
    ],
    ids=["not-orthonormal", "last-row", "far", "reflection"],
)
def test_a_bad_pose_is_named_as_before(documents, change, field, reason):
    document = copy.deepcopy(documents[3])
    change(document)
    with pytest.raises(LocalizationUpdateError) as new:
        parse_update(document)
    with pytest.raises(LocalizationUpdateError) as old:
        one_by_one(document)
    assert (new.value.field, str(new.value)) == (old.value.field, str(old.value))
    assert new.value.field == field
    assert reason in str(new.value)


def test_a_bad_pose_before_a_later_error_is_the_one_named(documents):
    document = copy.deepcopy(documents[3])
    document["poses"][1]["pose"][0] = 3.0  # not rigid, and before …
    document["poses"][3]["id"] = 0  # … ids going backwards, and …
    del document["poses"][4]["timestamp"]  # … a missing field
    with pytest.raises(LocalizationUpdateError) as err:
        parse_update(document)
    assert err.value.field == "poses[1].pose"
    document["poses"][1]["pose"][0] = documents[3]["poses"][1]["pose"][0]
    with pytest.raises(LocalizationUpdateError) as err:
        parse_update(document)
    assert err.value.field == "poses[3].id"
    document["poses"][3]["id"] = documents[3]["poses"][3]["id"]
    with pytest.raises(LocalizationUpdateError) as err:
        parse_update(document)
    assert err.value.field == "poses[4].timestamp"


def test_a_slightly_skewed_rotation_within_tolerance_is_accepted(documents):
    document = copy.deepcopy(documents[3])
    document["poses"][0]["pose"] = _rotated(document["poses"][0]["pose"], 0.2)
    assert np.array_equal(parse_update(document).session_T_phone, one_by_one(document))


def test_an_update_too_large_to_compute_in_a_moment_is_refused_before_it_is_read(documents):
    # An update's cost grows faster than its size, and an API process computes one at a time.
    pose = documents[3]["poses"][0]
    poses = [{**pose, "id": i, "timestamp": 0.1 * i} for i in range(MAX_UPDATE_POSES)]
    assert parse_update({"poses": poses}).num_poses == MAX_UPDATE_POSES
    too_many = [*poses, {"id": "not even read"}]
    with pytest.raises(LocalizationUpdateError) as err:
        parse_update({"poses": too_many})
    assert err.value.field == "poses"
    assert f"{MAX_UPDATE_POSES + 1} poses in one update, at most {MAX_UPDATE_POSES}" in str(
        err.value
    )

    detection = next(d for document in documents for frame in document["tag_data"] for d in frame)
    frames = [[detection] * 50] * (MAX_UPDATE_DETECTIONS // 50) + [detection]  # a bare one
    with pytest.raises(LocalizationUpdateError) as err:
        parse_update({"poses": [], "tag_data": frames})
    assert err.value.field == "tag_data"
    assert f"{MAX_UPDATE_DETECTIONS + 1} detections" in str(err.value)
