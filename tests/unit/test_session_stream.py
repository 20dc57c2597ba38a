"""The upload parser that reads JSON bytes as they come (``parse_session_stream``): the same
session, or the same error naming the same field, as ``parse_session(json.loads(...))``; the pose
limit reached before the rest is read; only a bounded window of text held."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.domain.errors import SessionFormatError
from app.domain.upload.fields import rigid_pose
from app.domain.upload.json_stream import JsonStream
from app.domain.upload.session import (
    Session,
    decode_json_bytes,
    parse_session,
    parse_session_stream,
)
from tests.unit.test_session import (
    DATA_DIR,
    VALID_PATHS,
    deleted,
    json_values,
    make_detection,
    make_upload,
    replaced,
    session_like,
    small_valid_upload,
)

SESSION_FILES = sorted((DATA_DIR / "sessions").glob("*.json"))
EARLIER_FORMAT_FILES = sorted((DATA_DIR / "archive").glob("*.json"))


def pieces(raw: bytes, size: int) -> Iterator[bytes]:
    return (raw[k : k + size] for k in range(0, len(raw), size))


def streamed(
    raw: bytes, *, size: int = 7, max_poses: int = 10**6, window_chars: int = 48
) -> Session:
    """Parsed from chunks of ``size`` bytes with a small window, so that values are cut by the
    ends of chunks and of the window."""
    return parse_session_stream(pieces(raw, size), max_poses=max_poses, window_chars=window_chars)


def outcome(parse: Any, *args: Any, **kwargs: Any) -> Session | tuple[str, str]:
    try:
        return parse(*args, **kwargs)  # type: ignore[no-any-return]
    except SessionFormatError as err:
        return (err.field, err.reason)


def assert_same_session(a: Session, b: Session) -> None:
    assert (a.map_id, a.warnings) == (b.map_id, b.warnings)
    for name in ("pose_id", "timestamp_s", "world_T_phone"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in a.detections.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a.detections, name), getattr(b.detections, name))
    assert [(p.name, p.pose_index, p.phone_T_poi.tolist()) for p in a.pois] == [
        (p.name, p.pose_index, p.phone_T_poi.tolist()) for p in b.pois
    ]


def assert_same_outcome(document: Any, *, size: int = 5) -> None:
    raw = json.dumps(document).encode()
    expected = outcome(parse_session, json.loads(raw))
    got = outcome(streamed, raw, size=size)
    if isinstance(expected, Session):
        assert isinstance(got, Session), got
        assert_same_session(got, expected)
    else:
        assert got == expected


# --------------------------------------------------------------------------- same sessions


@pytest.mark.parametrize("path", SESSION_FILES + EARLIER_FORMAT_FILES, ids=lambda p: p.name)
def test_every_real_session_parses_the_same_streamed(path: Path) -> None:
    raw = path.read_bytes()
    assert_same_session(streamed(raw, size=4093), parse_session(decode_json_bytes(raw)))


def test_a_session_cut_into_single_bytes_parses_the_same() -> None:
    raw = json.dumps(small_valid_upload(), indent=1, ensure_ascii=False).encode()
    assert_same_session(streamed(raw, size=1), parse_session(json.loads(raw)))


def test_a_multibyte_character_cut_between_chunks_is_read() -> None:
    document = small_valid_upload()
    document["map_id"] = "Café ☕ 地図"
    raw = json.dumps(document, ensure_ascii=False).encode()
    assert streamed(raw, size=1).map_id == "Café ☕ 地図"


def test_keys_the_parser_does_not_read_may_come_anywhere_and_hold_anything() -> None:
    document = {"plane_data": [[{"x": [1, 2]}]] * 3, "extra": {"a": [None, True]}}
    document |= small_valid_upload()
    document["tail"] = [1.5e300, "}", "]", '"']
    assert_same_outcome(document, size=3)


def test_tag_data_before_pose_data_is_read_whole_and_parsed_the_same() -> None:
    upload = small_valid_upload()
    document = {key: upload[key] for key in ("tag_data", "location_data", "pose_data", "map_id")}
    assert_same_outcome(document)
    document["tag_data"][0][0]["pose_id"] = 99
    assert_same_outcome(document)


def test_pose_data_given_again_after_streamed_tag_data_is_refused() -> None:
    raw = json.dumps(small_valid_upload()).encode()[:-1] + b', "pose_data": []}'
    with pytest.raises(SessionFormatError) as info:
        streamed(raw)
    assert info.value.field == "pose_data"


def test_many_detections_are_kept_in_blocks_and_joined_in_order() -> None:
    frames = [[make_detection(tag_id=k % 7, pose_id=k % 5)] for k in range(2500)]
    assert_same_outcome(make_upload(5, frames), size=997)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(VALID_PATHS), json_values)
def test_replacing_any_value_gives_the_same_outcome(path: tuple[Any, ...], value: Any) -> None:
    assert_same_outcome(replaced(small_valid_upload(), path, value))


@settings(max_examples=80, deadline=None)
@given(st.sampled_from(VALID_PATHS))
def test_deleting_any_value_gives_the_same_outcome(path: tuple[Any, ...]) -> None:
    assert_same_outcome(deleted(small_valid_upload(), path))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(session_like | json_values)
def test_arbitrary_documents_give_the_same_outcome(document: Any) -> None:
    assert_same_outcome(document, size=3)


def test_earlier_format_marker_with_current_rows_gives_the_same_error() -> None:
    document = small_valid_upload() | {"camera_intrinsics": "1460,1460,925,725,1,1920,1440"}
    assert_same_outcome(document)
    assert isinstance(outcome(parse_session, document), tuple)


# --------------------------------------------------------------------------- invalid JSON


@pytest.mark.parametrize("cut_share", [0, 0.001, 0.01, 0.3, 0.77, 0.9999])
def test_a_cut_document_is_the_same_json_error(cut_share: float) -> None:
    whole = json.dumps(small_valid_upload(), indent=2).encode()
    raw = whole[: int(len(whole) * cut_share)]
    expected = outcome(lambda: parse_session(decode_json_bytes(raw)))
    assert outcome(streamed, raw, size=64) == expected
    assert expected[0] == ""  # type: ignore[index]
    assert "not valid JSON" in expected[1]  # type: ignore[index]


@pytest.mark.parametrize(
    "raw",
    [
        b'{"map_id": "x",\n  "pose_data": [1 2]}',
        b'{"map_id": "x"} trailing',
        b'{"map_id" "x"}',
        b'{"map_id": "x",}',
        b'\n\n  {"pose_data": [{"id": 1,\n "timestamp": tru}]}',
        b"",
        b"   ",
        # newlines after the error (within the window), and one at the very start
        b'{"map_id": x\n\n\n}',
        b"{}x",  # an empty object, then one character more
        # errors far along a line whose start the window has dropped, on the first line and after
        b'{"map_id": "' + b"a" * 300 + b'", "pose_data": [1 2]}',
        b'{\n  "map_id": "' + b"a" * 300 + b'", "pose_data": [1 2]}',
        b'{\n\n  "map_id": "' + b"a" * 300 + b'", "x": [1 2],\n "pose_data": []}',
        b'\n{"map_id": "x", "pose_data": [1, x]\n\n\n}',
    ],
)
def test_syntax_errors_name_the_line_and_column_json_names(raw: bytes) -> None:
    expected = outcome(lambda: parse_session(decode_json_bytes(raw)))
    for size in (1, 3, 1000):
        for window_chars in (4, 1 << 16):
            with pytest.raises(SessionFormatError) as info:
                walk(JsonStream(pieces(raw, size), window_chars=window_chars))
            assert (info.value.field, info.value.reason) == expected


def walk(stream: JsonStream) -> None:
    """Read a document the way the parser does: keys, one array an element at a time."""
    for key in stream.object_keys():
        if key == "pose_data":
            list(stream.array_items())
        else:
            stream.skip_value()
    stream.end()


def test_bytes_that_are_not_utf8_are_a_format_error() -> None:
    with pytest.raises(SessionFormatError, match="not UTF-8"):
        streamed(b'{"map_id": "\xff\xfe"}', size=2)


def test_deep_nesting_is_a_format_error() -> None:
    with pytest.raises(SessionFormatError, match="nested too deeply"):
        streamed(b'{"map_id": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", size=4096)


# --------------------------------------------------------------------------- the pose limit


def test_more_poses_than_allowed_stop_the_reading_at_the_first_extra_pose() -> None:
    raw = json.dumps(make_upload(400)).encode()
    read: list[int] = []

    def counted() -> Iterator[bytes]:
        for chunk in pieces(raw, 256):
            read.append(len(chunk))
            yield chunk

    with pytest.raises(SessionFormatError) as info:
        parse_session_stream(counted(), max_poses=10, max_poses_name="INVISIBLE_MAP_MAX_POSES")
    assert info.value.field == "pose_data"
    assert "more than 10 poses" in info.value.reason
    assert "at most 10 (INVISIBLE_MAP_MAX_POSES)" in info.value.reason
    # with a window of 1 KiB, hardly more than the first 11 poses are read
    read.clear()
    with pytest.raises(SessionFormatError):
        parse_session_stream(counted(), max_poses=10, window_chars=1024)
    assert sum(read) < 11 * (len(raw) // 400) + 2 * 1024 + 256 < len(raw) / 10


def test_exactly_the_most_poses_allowed_are_accepted() -> None:
    raw = json.dumps(make_upload(10)).encode()
    assert streamed(raw, max_poses=10).num_poses == 10


def test_the_limit_is_checked_before_faults_in_the_poses() -> None:
    document = make_upload(12)
    document["pose_data"][3]["pose"] = "bad"
    with pytest.raises(SessionFormatError, match="more than 10 poses"):
        streamed(json.dumps(document).encode(), max_poses=10)
    assert outcome(streamed, json.dumps(document).encode(), max_poses=12) == outcome(
        parse_session, document
    )


# --------------------------------------------------------------------------- rigidity in blocks


def one_pose_upload(matrix: np.ndarray) -> dict[str, Any]:
    return {
        "map_id": "x",
        "pose_data": [{"id": 0, "timestamp": 0.0, "pose": matrix.flatten(order="F").tolist()}],
    }


@settings(max_examples=300, deadline=None)
@given(
    st.floats(min_value=-4, max_value=4),
    st.sampled_from([0.0, 1e-6, 1e-3, 0.004, 0.005, 0.0049999, 0.0050001, 0.01, 0.3]),
    st.sampled_from(["rotation", "last row", "translation", "reflection"]),
)
def test_poses_checked_in_blocks_are_refused_or_made_rigid_as_one_by_one(
    angle_rad: float, error: float, where: str
) -> None:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    matrix = np.array([[c, 0, s, 1.0], [0, 1, 0, 2.0], [-s, 0, c, 3.0], [0, 0, 0, 1.0]])
    if where == "rotation":
        matrix[:3, :3] *= 1 + error
    elif where == "last row":
        matrix[3, 0] += error
    elif where == "translation":
        matrix[0, 3] = 1e5 * (1 + error) - 1
    else:
        matrix[:3, 2] *= -1
    expected = outcome(rigid_pose, matrix, "pose_data[0].pose")
    got = outcome(parse_session, one_pose_upload(matrix))
    if isinstance(expected, tuple):
        assert got == expected
    else:
        assert isinstance(got, Session), got
        np.testing.assert_allclose(got.world_T_phone[0], expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("bad_row", [3, 4095, 4096, 9000])
def test_the_first_faulty_pose_is_reported_whichever_block_it_is_in(bad_row: int) -> None:
    document = make_upload(9_500)
    document["pose_data"][bad_row]["pose"][0] = 3.0  # not a rotation
    del document["pose_data"][bad_row + 7]["id"]  # a later fault of another kind
    expected = (f"pose_data[{bad_row}].pose", "rotation not orthonormal (entry 3 exceeds 1)")
    assert outcome(parse_session, document) == expected
    assert outcome(streamed, json.dumps(document).encode(), size=4096) == expected


def test_more_detections_than_the_pose_limit_are_refused_while_parsing() -> None:
    frames = [[make_detection(tag_id=3, pose_id=k % 5)] * 3 for k in range(4)]  # 12 detections
    raw = json.dumps(make_upload(5, frames)).encode()
    with pytest.raises(SessionFormatError) as info:
        parse_session_stream(
            pieces(raw, 64), max_poses=10, max_poses_name="INVISIBLE_MAP_MAX_POSES"
        )
    assert info.value.field == "tag_data"
    assert "more than 10 detections" in info.value.reason
    assert "INVISIBLE_MAP_MAX_POSES" in info.value.reason
    assert streamed(raw, max_poses=12).num_poses == 5


def test_a_top_level_array_is_passed_over_and_refused_as_no_object() -> None:
    raw = json.dumps([small_valid_upload()] * 50).encode()
    expected = outcome(parse_session, json.loads(raw))
    assert isinstance(expected, tuple)
    assert "expected a JSON object" in expected[1]
    assert outcome(streamed, raw) == expected
    assert outcome(streamed, raw[:-1]) == outcome(
        lambda: parse_session(decode_json_bytes(raw[:-1]))
    )


def test_pose_columns_grow_past_their_first_capacity(monkeypatch) -> None:
    """A stream starts its pose columns at ``_STREAM_CAPACITY`` rows (np.empty: pages cost
    only once written) and doubles them past it; the rows past the first capacity are kept."""
    import app.domain.upload.session as session_module

    monkeypatch.setattr(session_module, "_STREAM_CAPACITY", 3)
    document = make_upload(num_poses=13)  # grows 3 → 6 → 12 → 24
    expected = parse_session(document)
    got = streamed(json.dumps(document).encode(), size=64)
    assert got.num_poses == 13
    assert_same_session(got, expected)


def test_the_limits_refusal_names_max_poses_by_default_and_the_source_in_syntax_errors() -> None:
    with pytest.raises(SessionFormatError) as info:
        streamed(json.dumps(make_upload(12)).encode(), max_poses=10)
    assert "at most 10 (max_poses)" in info.value.reason
    with pytest.raises(SessionFormatError) as info:
        parse_session_stream(pieces(b'{"map_id": x}', 4), max_poses=10, source="walk.json")
    assert info.value.reason == "walk.json is not valid JSON: Expecting value at line 1 column 12"


def test_pose_data_after_tag_data_a_second_time_is_refused_by_name() -> None:
    document = small_valid_upload()
    raw = json.dumps(document)[:-1] + ', "pose_data": []}'
    with pytest.raises(SessionFormatError) as info:
        streamed(raw.encode())
    assert (info.value.field, info.value.reason) == (
        "pose_data",
        "given twice, the second after tag_data",
    )


@pytest.mark.parametrize("correct", [True, False])
def test_the_poi_correction_reaches_sessions_read_whole_from_a_stream(correct: bool) -> None:
    """Sections in an order the app does not write (``tag_data`` first) are decoded whole and
    parsed as before: the point of interest's pose id corrected as asked."""
    from tests.unit.test_session import make_location

    document = make_upload(locations=[make_location("door", 4)])
    reordered = {"tag_data": document["tag_data"], **document}
    raw = json.dumps(reordered).encode()
    got = parse_session_stream(pieces(raw, 64), max_poses=100, correct_poi_pose_id=correct)
    assert got.pois[0].pose_index == (3 if correct else 4)


@pytest.mark.parametrize("correct", [True, False])
def test_the_poi_correction_reaches_earlier_format_sessions_from_a_stream(correct: bool) -> None:
    from tests.unit.test_session import make_location

    document = json.loads((DATA_DIR / "archive" / "round2.json").read_text())
    pose_id = int(document["pose_data"][5][17])
    document["location_data"] = [make_location("door", pose_id)]
    raw = json.dumps(document).encode()
    got = parse_session_stream(pieces(raw, 4096), max_poses=10**5, correct_poi_pose_id=correct)
    assert got.pois[0].pose_index == (4 if correct else 5)
    assert (
        got.pois[0].pose_index
        == parse_session(document, correct_poi_pose_id=correct).pois[0].pose_index
    )


def test_an_integer_of_too_many_digits_is_refused_as_the_whole_document_refuses_it() -> None:
    raw = b'{"map_id": "x", "pose_data": [' + b"9" * 5000 + b"]}"
    expected = outcome(lambda: parse_session(decode_json_bytes(raw)))
    assert expected[0] == ""  # type: ignore[index]
    assert expected[1] == (  # type: ignore[index]
        "upload is not valid JSON: Exceeds the limit (4300 digits) for integer string conversion"
    )
    for window_chars in (48, 1 << 16):
        assert outcome(streamed, raw, size=512, window_chars=window_chars) == expected
