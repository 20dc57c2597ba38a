"""SLAM parameters: documented defaults, ``--param NAME=VALUE`` parsing, validation, round trips."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.domain.errors import InvisibleMapError, ParameterError
from app.domain.evaluation.tuning import PAPER_GRID_RANGE
from app.domain.mapping.params import (
    DEFAULT_TAG_SIZE_M,
    PARAM_RANGES,
    TAG_SIZE_RANGE,
    ParamRange,
    SlamParams,
)

VARIANCES = (
    "tag_position_var_m2",
    "tag_orientation_var_rad2",
    "odom_linear_var_m2_per_s",
    "odom_angular_var_rad2_per_s",
    "gravity_var_rad2",
)
ALL_NAMES = sorted(f.name for f in dataclasses.fields(SlamParams))


# --------------------------------------------------------------------------- defaults


def test_defaults_are_valid_and_documented_values():
    params = SlamParams()
    assert params.tag_size_m == DEFAULT_TAG_SIZE_M == pytest.approx(0.173)
    assert params.tag_sizes_m == {}
    for name in VARIANCES:
        value = getattr(params, name)
        assert isinstance(value, float)
        assert 0 < value < math.inf
    assert params.tag_depth_var_ratio >= 1
    assert params.huber_k >= 0
    assert 0 < params.max_view_angle_deg <= 90
    assert params.max_iterations >= 1
    assert isinstance(params.compute_marginals, bool)


def test_defaults_survive_their_own_validation():
    params = SlamParams()
    assert dataclasses.replace(params) == params


def test_params_are_frozen_and_keyword_only():
    params = SlamParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.tag_position_var_m2 = 1.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        SlamParams(1e-4)  # type: ignore[misc]


def test_parameter_error_is_an_invisible_map_error():
    assert issubclass(ParameterError, InvisibleMapError)


# --------------------------------------------------------------------------- with_overrides


def test_with_overrides_parses_float_strings():
    params = SlamParams().with_overrides(
        {"tag_position_var_m2": "1e-4", "odom_linear_var_m2_per_s": " 2.5e-3 "}
    )
    assert params.tag_position_var_m2 == 1e-4
    assert params.odom_linear_var_m2_per_s == 2.5e-3
    assert isinstance(params.tag_position_var_m2, float)


def test_with_overrides_leaves_the_original_and_other_fields_alone():
    original = SlamParams()
    changed = original.with_overrides({"huber_k": "0"})
    assert original.huber_k == SlamParams().huber_k
    assert changed.huber_k == 0.0  # 0 disables Huber and is allowed
    assert dataclasses.replace(changed, huber_k=original.huber_k) == original


def test_with_overrides_accepts_numbers():
    params = SlamParams().with_overrides({"gravity_var_rad2": 0.5, "max_iterations": 7})
    assert params.gravity_var_rad2 == 0.5
    assert params.max_iterations == 7


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("true", True),
        ("True", True),
        ("1", True),
        ("yes", True),
        ("on", True),
        ("false", False),
        ("FALSE", False),
        ("0", False),
        ("no", False),
        ("off", False),
    ],
)
def test_with_overrides_parses_booleans(text, expected):
    params = SlamParams().with_overrides({"compute_marginals": text})
    assert params.compute_marginals is expected


def test_with_overrides_accepts_real_booleans():
    assert SlamParams().with_overrides({"compute_marginals": False}).compute_marginals is False


def test_with_overrides_parses_ints():
    params = SlamParams().with_overrides({"max_iterations": "25"})
    assert params.max_iterations == 25
    assert isinstance(params.max_iterations, int)


@pytest.mark.parametrize("value", ["1.5", 1.5, "ten", ""])
def test_with_overrides_rejects_non_integers_for_ints(value):
    with pytest.raises(ParameterError, match="max_iterations"):
        SlamParams().with_overrides({"max_iterations": value})


def test_with_overrides_rejects_bad_booleans():
    with pytest.raises(ParameterError, match="compute_marginals"):
        SlamParams().with_overrides({"compute_marginals": "maybe"})


def test_unknown_name_lists_known_ones():
    with pytest.raises(ParameterError) as info:
        SlamParams().with_overrides({"nonsense": "1"})
    message = str(info.value)
    assert "'nonsense'" in message
    for name in ALL_NAMES:
        assert name in message
    assert "\n" not in message


def test_unknown_name_is_rejected_even_next_to_valid_ones():
    with pytest.raises(ParameterError, match="tag_position_var"):
        SlamParams().with_overrides({"huber_k": "1", "tag_position_var": "1e-4"})


@pytest.mark.parametrize("value", ["abc", "1e-4x", "", "one", "--1"])
def test_non_numeric_values_are_rejected(value):
    with pytest.raises(ParameterError) as info:
        SlamParams().with_overrides({"tag_position_var_m2": value})
    assert "tag_position_var_m2" in str(info.value)
    assert repr(value) in str(info.value)


def test_bool_is_not_a_float():
    with pytest.raises(ParameterError, match="huber_k"):
        SlamParams().with_overrides({"huber_k": True})


@pytest.mark.parametrize("name", VARIANCES)
@pytest.mark.parametrize("value", ["-1", "0", "-1e-9", -2.0, 0])
def test_variances_must_be_positive(name, value):
    with pytest.raises(ParameterError) as info:
        SlamParams().with_overrides({name: value})
    assert name in str(info.value)
    assert "> 0" in str(info.value)


@pytest.mark.parametrize("name", [*VARIANCES, "huber_k", "tag_size_m", "max_distance_m"])
@pytest.mark.parametrize("value", ["nan", "NaN", "inf", "-inf", math.nan, math.inf])
def test_non_finite_values_are_rejected(name, value):
    with pytest.raises(ParameterError) as info:
        SlamParams().with_overrides({name: value})
    assert name in str(info.value)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("tag_depth_var_ratio", "0.5"),
        ("huber_k", "-1"),
        ("max_view_angle_deg", "0"),
        ("max_view_angle_deg", "91"),
        ("max_iterations", "0"),
        ("max_reprojection_px", "0"),
        ("max_distance_m", "-3"),
        ("tag_size_m", "0"),
        ("relative_error_tol", "0"),
        ("keyframe_interval_s", "-1"),
        ("noise_prior_dof", "-1"),
    ],
)
def test_out_of_range_values_are_rejected(name, value):
    with pytest.raises(ParameterError, match=name):
        SlamParams().with_overrides({name: value})


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("tag_depth_var_ratio", "1"),
        ("max_view_angle_deg", "90"),
        ("max_iterations", "1"),
        # 0 means something for these: every pose kept, the prior off; so does the off value
        ("keyframe_interval_s", "0"),
        ("noise_prior_dof", "0"),
        ("huber_k", "0"),
        ("stairs_yaw_var_rad2_per_m", "0"),
        ("keyframe_interval_s", "3600"),
        ("huber_k", "100"),
    ],
)
def test_range_boundaries_are_accepted(name, value):
    params = SlamParams().with_overrides({name: value})
    assert getattr(params, name) == float(value)


def test_constructor_validates_too():
    with pytest.raises(ParameterError, match="tag_orientation_var_rad2"):
        SlamParams(tag_orientation_var_rad2=-1.0)
    with pytest.raises(ParameterError, match="gravity_var_rad2"):
        SlamParams(gravity_var_rad2=math.nan)


# --------------------------------------------------------------------------- tag sizes


def test_tag_sizes_from_string():
    params = SlamParams().with_overrides({"tag_sizes_m": "300:0.15,301:0.2"})
    assert params.tag_sizes_m == {300: 0.15, 301: 0.2}
    assert params.tag_size_for(300) == 0.15
    assert params.tag_size_for(301) == 0.2
    assert params.tag_size_for(302) == DEFAULT_TAG_SIZE_M
    assert isinstance(params.tag_size_for(300), float)


def test_tag_sizes_string_tolerates_spaces_and_trailing_comma():
    params = SlamParams().with_overrides({"tag_sizes_m": " 7:0.1 , 8:0.25,"})
    assert params.tag_sizes_m == {7: 0.1, 8: 0.25}


def test_tag_sizes_empty_string_means_none():
    assert SlamParams().with_overrides({"tag_sizes_m": ""}).tag_sizes_m == {}


def test_tag_sizes_from_mapping_with_string_keys():
    params = SlamParams().with_overrides({"tag_sizes_m": {"5": "0.3"}})
    assert params.tag_sizes_m == {5: 0.3}
    assert params.tag_size_for(5) == 0.3


def test_default_tag_size_follows_tag_size_m():
    params = SlamParams().with_overrides({"tag_size_m": "0.2", "tag_sizes_m": "1:0.1"})
    assert params.tag_size_for(1) == 0.1
    assert params.tag_size_for(2) == 0.2


@pytest.mark.parametrize("text", ["abc", "300", "300:0.1:2", "x:0.1", "300:big"])
def test_tag_sizes_malformed_strings_are_rejected(text):
    with pytest.raises(ParameterError, match="tag_sizes_m"):
        SlamParams().with_overrides({"tag_sizes_m": text})


@pytest.mark.parametrize("text", ["300:0", "300:-0.1", "300:nan", "300:inf"])
def test_tag_sizes_must_be_positive_and_finite(text):
    with pytest.raises(ParameterError, match="tag_sizes_m"):
        SlamParams().with_overrides({"tag_sizes_m": text})


# --------------------------------------------------------------------------- dict round trip


def test_to_dict_has_every_field_and_is_json_ready():
    params = SlamParams().with_overrides({"tag_sizes_m": "300:0.15,301:0.2"})
    out = params.to_dict()
    assert sorted(out) == ALL_NAMES
    assert out["tag_sizes_m"] == {"300": 0.15, "301": 0.2}
    assert json.loads(json.dumps(out, allow_nan=False)) == out


def test_to_dict_from_dict_round_trip():
    params = SlamParams().with_overrides(
        {
            "tag_position_var_m2": "3e-5",
            "compute_marginals": "false",
            "max_iterations": "12",
            "tag_sizes_m": "300:0.15,301:0.2",
        }
    )
    restored = SlamParams.from_dict(json.loads(json.dumps(params.to_dict())))
    assert restored == params
    assert restored.tag_sizes_m == {300: 0.15, 301: 0.2}
    assert restored.compute_marginals is False


def test_from_dict_of_defaults_is_defaults():
    assert SlamParams.from_dict(SlamParams().to_dict()) == SlamParams()
    assert SlamParams.from_dict({}) == SlamParams()


def test_from_dict_rejects_unknown_names():
    values = SlamParams().to_dict()
    values["legacy_param"] = 1
    with pytest.raises(ParameterError, match="legacy_param"):
        SlamParams.from_dict(values)


positive_floats = st.floats(min_value=1e-12, max_value=1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=100, deadline=None)
@given(
    tag_position=positive_floats,
    odom_angular=positive_floats,
    view_deg=st.floats(min_value=0.1, max_value=90.0),
    iterations=st.integers(min_value=1, max_value=10_000),
    marginals=st.booleans(),
    sizes=st.dictionaries(st.integers(min_value=0, max_value=600), positive_floats, max_size=4),
)
def test_round_trip_property(tag_position, odom_angular, view_deg, iterations, marginals, sizes):
    params = SlamParams(
        tag_position_var_m2=tag_position,
        odom_angular_var_rad2_per_s=odom_angular,
        max_view_angle_deg=view_deg,
        max_iterations=iterations,
        compute_marginals=marginals,
        tag_sizes_m=sizes,
    )
    assert SlamParams.from_dict(json.loads(json.dumps(params.to_dict()))) == params
    # Through strings too, as --param passes them.
    as_text = {k: str(v) for k, v in params.to_dict().items() if k != "tag_sizes_m"}
    assert SlamParams().with_overrides(as_text) == dataclasses.replace(params, tag_sizes_m={})


# --------------------------------------------------------------------------- ranges (issue 40)

#: Values from outside that no setting means, and a word of the range the error must name.
OUT_OF_RANGE = [
    ("huber_k", "1e308", "0.1 to 100"),
    ("huber_k", 1e308, "0.1 to 100"),
    ("huber_k", "0.01", "0 (off) or 0.1 to 100 σ"),
    ("huber_k", "-1", "0 (off) or 0.1 to 100 σ"),
    ("huber_k", "NaN", "0 (off) or 0.1 to 100 σ"),
    ("tag_position_var_m2", "1e308", "1e-12 to 1e+06 m²"),
    ("tag_position_var_m2", "0", "1e-12 to 1e+06 m²"),
    ("tag_position_var_m2", "1e-300", "1e-12 to 1e+06 m²"),
    ("odom_linear_var_m2_per_s", "-1e-3", "1e-12 to 1e+06 m²/s"),
    ("odom_angular_var_rad2_per_s", "nan", "1e-12 to 1e+06 rad²/s"),
    ("tag_orientation_var_rad2", "1e7", "1e-12 to 1e+06 rad²"),
    ("gravity_var_rad2", "inf", "1e-12 to 1e+06 rad²"),
    ("tag_depth_var_ratio", "1e308", "1 to 1e+06"),
    ("noise_prior_dof", "1e308", "0 to 1e+06"),
    ("max_reprojection_px", "1e308", "0.1 to 10000 px"),
    ("max_view_angle_deg", "0.5", "1 to 90 degrees"),
    ("max_distance_m", "1e308", "0.01 to 1000 m"),
    ("keyframe_interval_s", "1e308", "0 to 3600 s"),
    ("tag_size_m", "1e308", "0.001 to 10 m"),
    ("max_iterations", "10001", "1 to 10000"),
    ("max_iterations", "1" + "0" * 400, "1 to 10000"),
    ("max_iterations", 1e308, "1 to 10000"),
    ("converged_step_m", "1e3", "1e-12 to 1 m"),
    ("converged_step_rad", "0", "1e-12 to 1 rad"),
    ("relative_error_tol", "2", "1e-16 to 1"),
    ("keyframe_interval_s", "3601", "0 to 3600 s"),
    ("huber_k", "0.05", "0 (off) or 0.1 to 100"),  # between off and the range
    ("stairs_yaw_var_rad2_per_m", "1e-9", "0 (off) or 1e-08 to 1 rad²/m"),
    ("stairs_linear_var_m2_per_m", "2", "0 (off) or 1e-08 to 1 m²/m"),
    ("tag_sizes_m", "300:1e308", "0.001 to 10 m"),
    ("tag_sizes_m", {"-1": 0.15}, "0 to 2147483647"),
    ("tag_sizes_m", {str(2**31): 0.15}, "0 to 2147483647"),
]


@pytest.mark.parametrize(("name", "value", "range_text"), OUT_OF_RANGE)
def test_a_value_from_outside_must_lie_in_its_range(name, value, range_text):
    with pytest.raises(ParameterError) as info:
        SlamParams().with_checked_overrides({name: value})
    message = str(info.value)
    assert name in message
    assert range_text in message
    assert len(message) < 200  # one readable line, even for 400 digits
    assert "\n" not in message


def test_a_range_check_leaves_the_solvers_own_checks_alone():
    # A map stored with a value out of range is still read (from_dict does not check ranges),
    # and the domain's code and tests may use any value the solver takes.
    params = SlamParams.from_dict({"huber_k": 1e308, "max_iterations": 10**6})
    assert params.huber_k == 1e308
    with pytest.raises(ParameterError, match=r"huber_k must be 0 \(off\) or 0\.1 to 100"):
        params.check_ranges()


def test_every_number_has_a_range_and_the_defaults_lie_in_theirs():
    defaults = SlamParams()
    numbers = {
        f.name
        for f in dataclasses.fields(SlamParams)
        if isinstance(getattr(defaults, f.name), (int, float))
        and not isinstance(getattr(defaults, f.name), bool)
    }
    assert numbers == set(PARAM_RANGES)
    assert defaults.check_ranges() is defaults
    assert DEFAULT_TAG_SIZE_M in TAG_SIZE_RANGE


@pytest.mark.parametrize(
    ("name", "value"),
    [
        # every value a sweep tries: the paper's grid (1e-10 … 10) and ours (1e-8 … 1)
        *((name, bound) for name in VARIANCES for bound in (1e-10, 10.0, *PAPER_GRID_RANGE)),
        ("huber_k", 0),  # off
        ("huber_k", "0.0"),
        ("huber_k", 1.345),
        ("huber_k", 2.0),
        ("max_reprojection_px", 1000),  # docs/tuning.md
        ("max_distance_m", 0.01),
        ("keyframe_interval_s", 0),  # every pose
        ("noise_prior_dof", 0.0),
        ("stairs_yaw_var_rad2_per_m", 0),  # off, the default
        ("stairs_yaw_var_rad2_per_m", 1.5e-3),  # docs/multi-session.md, issue 37
        ("stairs_linear_var_m2_per_m", 3e-2),
        ("max_iterations", 10_000),
        ("max_iterations", 1),
        ("max_view_angle_deg", 90),
        ("relative_error_tol", 1e-3),
        ("tag_sizes_m", "300:0.15,301:0.2"),
        ("tag_sizes_m", ""),
    ],
)
def test_values_in_use_lie_in_their_ranges(name, value):
    SlamParams().with_checked_overrides({name: value})


def test_a_range_reads_as_its_error_says_it():
    assert str(ParamRange(0.1, 100.0, "σ", off=0.0)) == "0 (off) or 0.1 to 100 σ"
    assert str(ParamRange(1, 10_000)) == "1 to 10000"
    assert 0.0 in ParamRange(0.1, 100.0, off=0.0)
    assert 0.05 not in ParamRange(0.1, 100.0, off=0.0)
    assert math.nan not in ParamRange(0.0, 1.0)


def test_a_value_that_cannot_be_read_is_shown_briefly():
    with pytest.raises(ParameterError) as info:
        SlamParams().with_checked_overrides({"max_iterations": "9" * 5000})
    assert len(str(info.value)) < 300
