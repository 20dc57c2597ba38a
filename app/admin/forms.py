"""The dashboard's form fields that carry more than one value: the rebuild form's SLAM parameters
and the route tester's endpoints.

    fields = rebuild_fields(current_params)          # what the form shows, prefilled
    overrides = rebuild_overrides(form)              # InvalidInput naming a bad parameter
    parse_endpoint("tag:5"), parse_endpoint("poi:Room 209"), parse_endpoint("pos:1.5,0,-2")
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from app.domain.mapping.params import SlamParams
from app.domain.navigation.routing import Endpoint, NodeEnd, PoiEnd, PositionEnd, TagEnd
from app.services.errors import InvalidInput
from app.services.maps import checked_overrides


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamField:
    """One SLAM parameter in the rebuild form."""

    name: str
    label: str
    unit: str
    value: str = ""


#: The parameters the rebuild form offers (every SlamParams field), in the form's order.
REBUILD_PARAMS = (
    ParamField(name="tag_position_var_m2", label="Tag position variance at 1 m", unit="m²"),
    ParamField(name="tag_depth_var_ratio", label="Depth-to-lateral variance ratio", unit="≥ 1"),
    ParamField(name="tag_orientation_var_rad2", label="Tag orientation variance", unit="rad²"),
    ParamField(name="odom_linear_var_m2_per_s", label="Odometry linear variance", unit="m²/s"),
    ParamField(
        name="odom_angular_var_rad2_per_s", label="Odometry angular variance", unit="rad²/s"
    ),
    ParamField(name="gravity_var_rad2", label="Gravity variance", unit="rad²"),
    ParamField(name="huber_k", label="Huber threshold, 0 for none", unit="σ"),
    ParamField(name="max_reprojection_px", label="Largest reprojection error", unit="px"),
    ParamField(name="max_view_angle_deg", label="Largest view angle", unit="degrees"),
    ParamField(name="max_distance_m", label="Largest tag distance", unit="m"),
    ParamField(name="tag_size_m", label="Tag size", unit="m"),
    ParamField(name="tag_sizes_m", label="Tag sizes by id, like 300:0.15,301:0.2", unit="m"),
    ParamField(name="max_iterations", label="Most iterations", unit="count"),
    ParamField(name="relative_error_tol", label="Relative error tolerance", unit="fraction"),
    ParamField(name="compute_marginals", label="Compute tag covariances", unit="true or false"),
)


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Mapping):
        return ",".join(f"{tag}:{size:g}" for tag, size in value.items())
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def rebuild_fields(
    params: Mapping[str, Any] | None, submitted: Mapping[str, str] | None = None
) -> list[ParamField]:
    """The form's fields with the values to show: what was submitted (after an error), else the
    given version's parameters, else the defaults."""
    values = {**SlamParams().to_dict(), **(params or {})}
    return [
        ParamField(
            name=field.name,
            label=field.label,
            unit=field.unit,
            value=submitted[field.name]
            if submitted is not None and field.name in submitted
            else _shown(values.get(field.name, "")),
        )
        for field in REBUILD_PARAMS
    ]


def rebuild_overrides(form: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    """The parameters of a rebuild form that differ from the defaults (checked as the API
    checks them: InvalidInput naming the parameter), and the submitted texts."""
    submitted = {
        field.name: str(form.get(field.name, "")).strip()
        for field in REBUILD_PARAMS
        if field.name in form
    }
    given: dict[str, Any] = {name: text for name, text in submitted.items() if text}
    if "tag_sizes_m" in submitted and not submitted["tag_sizes_m"]:
        given["tag_sizes_m"] = ""
    checked = checked_overrides(given)
    defaults = SlamParams().to_dict()
    return {name: value for name, value in checked.items() if value != defaults[name]}, submitted


def parse_endpoint(text: str, what: str) -> Endpoint:
    """A route end from the route tester: ``tag:ID``, ``poi:NAME``, ``node:ID`` or
    ``pos:X,Y,Z`` (m, map frame). InvalidInput for anything else, naming ``what`` ("From")."""
    kind, _, value = text.partition(":")
    value = value.strip()
    try:
        if kind == "tag":
            return TagEnd(int(value))
        if kind == "node":
            return NodeEnd(int(value))
        if kind == "poi" and value:
            return PoiEnd(value)
        if kind == "pos":
            x, y, z = (float(part) for part in value.split(","))
            if all(abs(c) < 1e6 for c in (x, y, z)):
                return PositionEnd((x, y, z))
    except ValueError:
        pass
    raise InvalidInput(
        "invalid_route",
        f"{what}: choose a tag, a point of interest or a place on the map (got {text!r})",
        field=what.lower(),
    )


def changed_params(params: Mapping[str, Any]) -> list[str]:
    """``name = value`` of each parameter that differs from the defaults, for a versions table."""
    defaults = SlamParams().to_dict()
    return [
        f"{name} = {_shown(value)}"
        for name, value in params.items()
        if name in defaults and value != defaults[name]
    ]
