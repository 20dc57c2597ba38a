"""What limits the ground-truth metric on the real sessions (issue 4's accuracy targets).

    .venv/bin/python bench/ground_truth_limits.py        # a few seconds

(1) Per session, the map with the default parameters: its ground-truth metric; the same map with
    each tag's orientation replaced by the ground truth's (positions kept; the ground truth turned
    into the map by the best rigid fit of the tag positions), and with each position replaced
    (orientations kept); and the median angle between each tag's orientation and the ground
    truth's. The anchor alignment of the metric turns the whole ground truth by the anchor tag's
    orientation error, so the metric is roughly the mean orientation error in radians plus the
    position errors over the distances.
(2) Per ground-truth file: how far its tags lean off vertical (a tag on a wall has its +y up), and
    the ground-truth metric of the ground truth with only that lean removed, scored against the
    ground truth itself: what a perfect map could not get below if the tags really hang straight.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth  # noqa: E402
from app.domain.evaluation.metrics import compare_tag_sets, ground_truth_metric, umeyama_rigid  # noqa: E402
from app.domain.frames import FloatArray, rotation_angle_rad  # noqa: E402
from app.domain.mapping.slam import WORLD_UP, optimize_session  # noqa: E402
from app.domain.upload.session import load_session  # noqa: E402
from bench.tuning import REAL  # noqa: E402  (the real sessions with ground truth)

DATA = REPO / "data"
GROUND_TRUTHS = ("rtabmap_mac_1_2.txt", "occam_room_tape.json")


def map_T_gt(map_T_tag: dict[int, FloatArray], gt_T_tag: dict[int, FloatArray]) -> FloatArray:
    """The best rigid fit of the common tags' ground-truth positions to the map's."""
    common = compare_tag_sets(map_T_tag, gt_T_tag).common
    gt_xyz = np.array([gt_T_tag[t][:3, 3] for t in common])
    map_xyz = np.array([map_T_tag[t][:3, 3] for t in common])
    return umeyama_rigid(gt_xyz, map_xyz)


def with_truth(
    map_T_tag: dict[int, FloatArray], gt_T_tag: dict[int, FloatArray], part: str
) -> dict[int, FloatArray]:
    """The map with each common tag's orientation ("rotation") or position ("position") taken
    from the ground truth, fitted into the map."""
    fit = map_T_gt(map_T_tag, gt_T_tag)
    out = {}
    for tag_id in compare_tag_sets(map_T_tag, gt_T_tag).common:
        pose = map_T_tag[tag_id].copy()
        fitted = fit @ gt_T_tag[tag_id]
        if part == "rotation":
            pose[:3, :3] = fitted[:3, :3]
        else:
            pose[:3, 3] = fitted[:3, 3]
        out[tag_id] = pose
    return out


def orientation_errors_deg(
    map_T_tag: dict[int, FloatArray], gt_T_tag: dict[int, FloatArray]
) -> FloatArray:
    fit = map_T_gt(map_T_tag, gt_T_tag)
    return np.array(
        [
            math.degrees(rotation_angle_rad((fit @ gt_T_tag[t])[:3, :3].T @ map_T_tag[t][:3, :3]))
            for t in compare_tag_sets(map_T_tag, gt_T_tag).common
        ]
    )


def upright(world_T_tag: FloatArray) -> FloatArray:
    """The pose with its +y turned up, its normal (+z) kept in the same horizontal direction."""
    normal = world_T_tag[:3, 2].copy()
    normal[1] = 0.0
    normal /= np.linalg.norm(normal)
    pose = world_T_tag.copy()
    pose[:3, :3] = np.column_stack([np.cross(WORLD_UP, normal), WORLD_UP, normal])
    return pose


def lean_deg(world_T_tag: FloatArray) -> float:
    return math.degrees(math.acos(min(1.0, float(world_T_tag[:3, 1] @ WORLD_UP))))


def main() -> int:
    rows = [
        [
            "session",
            "tags",
            "GT metric",
            "… with the truth's orientations",
            "… with the truth's positions",
            "orientation error median °",
        ]
    ]
    for name, gt_file in REAL:
        session = load_session(DATA / "sessions" / f"{name}.json")
        truth = load_ground_truth(DATA / "ground_truth" / gt_file)
        tags = optimize_session(session).tag_poses()
        rows.append(
            [
                name,
                str(len(compare_tag_sets(tags, truth).common)),
                f"{ground_truth_metric(tags, truth):.4f}",
                f"{ground_truth_metric(with_truth(tags, truth, 'rotation'), truth):.4f}",
                f"{ground_truth_metric(with_truth(tags, truth, 'position'), truth):.4f}",
                f"{np.median(orientation_errors_deg(tags, truth)):.2f}",
            ]
        )
    print("(1) The default maps against ground truth\n")
    print(render_markdown_table(rows, justify="right"))

    rows = [["ground truth", "tags", "lean off vertical ° (min / mean / max)", "upright vs itself"]]
    for gt_file in GROUND_TRUTHS:
        truth = load_ground_truth(DATA / "ground_truth" / gt_file)
        leans = np.array([lean_deg(pose) for pose in truth.values()])
        straightened = {tag_id: upright(pose) for tag_id, pose in truth.items()}
        rows.append(
            [
                gt_file,
                str(len(truth)),
                f"{leans.min():.1f} / {leans.mean():.1f} / {leans.max():.1f}",
                f"{ground_truth_metric(straightened, truth):.4f}",
            ]
        )
    print("\n(2) The ground truth's own tags\n")
    print(render_markdown_table(rows, justify="right"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
