"""The ``--param NAME=VALUE`` option the commands share."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from app.domain.errors import ParameterError
from app.domain.params import SlamParams


def add_param_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a SLAM parameter (see SlamParams), e.g. tag_position_var_m2=1e-4",
    )


def slam_params(pairs: Sequence[str]) -> SlamParams:
    overrides = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or not name.strip():
            raise ParameterError(f"--param expects NAME=VALUE, got {pair!r}")
        overrides[name.strip()] = value.strip()
    return SlamParams().with_overrides(overrides)
