"""The dashboard's note on the shift metric says which way optimizing moves it, as the shipped
walks show: the optimized map's figure is lower than the pre-optimized one on most of them."""

from __future__ import annotations

import math
import re

from app.admin.templating import templates
from app.cli.common import DATA_DIR, DEMO_SESSIONS
from app.domain.evaluation.table import evaluate_map
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import load_session


def shift_note() -> str:
    macros = templates.env.get_template("_macros.html").module
    return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", str(macros.shift_explained())))  # type: ignore[attr-defined]


def test_the_note_says_the_optimized_shift_metric_is_usually_lower_as_the_demo_walks_show():
    lower = higher = 0
    for name, _ in DEMO_SESSIONS:
        session = load_session(DATA_DIR / "sessions" / f"{name}.json")
        evaluation = evaluate_map(session, optimize_session(session, SlamParams()))
        if math.isnan(evaluation.shift_pre) or math.isnan(evaluation.shift_opt):
            continue  # fewer than two tags: no pair of tags to compare
        lower += evaluation.shift_opt < evaluation.shift_pre
        higher += evaluation.shift_opt > evaluation.shift_pre
    assert lower > higher, (lower, higher)  # what the note must then say
    note = shift_note()
    assert "usually lower" in note, note
    assert "higher" not in note.split("usually lower", 1)[0], note
    assert f"on {lower} of the {lower + higher} demo walks" in note, note  # the count shown
