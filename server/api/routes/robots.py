"""``GET /v1/robots`` and ``GET /v1/robots/{robot_id}/trajectory``: robots, their anchoring on
the map, and their camera paths (on the map or in their odom frames)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import PlainTextResponse

from wardmap.server.api.deps import StoreDep
from wardmap.server.api.schemas import ErrorOut, PoseOut, RobotList, RobotOut, TrajectoryOut, TransformOut
from wardmap.shared.se3 import transform_to_tum

router = APIRouter()


def _pose(stamp: float, T: np.ndarray) -> PoseOut:
    row = transform_to_tum(T)
    return PoseOut(stamp=float(stamp), t=[float(v) for v in row[:3]], q_xyzw=[float(v) for v in row[3:]])


def _transform(T: np.ndarray) -> TransformOut:
    row = transform_to_tum(T)
    return TransformOut(t=[float(v) for v in row[:3]], q_xyzw=[float(v) for v in row[3:]])


@router.get("/v1/robots", response_model=RobotList)
def robots(store: StoreDep) -> RobotList:
    anchors = {(a.robot_id, a.session_id): a for a in store.session_anchors()}
    latest = store.latest_nodes()
    out = []
    for r in store.robots():
        node = latest.get(r.robot_id)
        fields: dict[str, Any] = {}
        if node is not None:
            anchor = anchors.get((node.key[0], node.key[1]))
            fields["session_id"] = node.key[1]
            if anchor is not None and anchor.T_map_odom is not None:
                fields.update(anchored=True, anchored_at_s=anchor.anchored_s, anchored_to=anchor.anchored_to,
                              T_map_odom=_transform(anchor.T_map_odom))
            if node.T_map_camera is not None:
                fields["map_pose"] = _pose(node.stamp, node.T_map_camera)
        out.append(RobotOut(robot_id=r.robot_id, keyframes=r.keyframes, sessions=r.sessions,
                            first_seen_s=r.first_seen_s, last_seen_s=r.last_seen_s, **fields))
    return RobotList(robots=out)


@router.get(
    "/v1/robots/{robot_id}/trajectory",
    response_model=None,
    responses={200: {"model": TrajectoryOut}, 404: {"model": ErrorOut}},
)
def trajectory(
    store: StoreDep,
    robot_id: str,
    format: Annotated[Literal["tum", "json"], Query()] = "json",
    frame: Annotated[Literal["map", "odom"], Query()] = "map",
) -> Any:
    """The keyframe trajectory: ``frame=map`` (default) the back-end's optimised camera poses of
    the robot's anchored sessions; ``frame=odom`` the poses it tracked, each session in its own
    odom frame."""
    stamps, T = store.trajectory(robot_id)
    if len(stamps) == 0:
        raise HTTPException(404, f"unknown robot {robot_id!r}")
    if frame == "map":
        stamps, T = store.map_trajectory(robot_id)
    if format == "tum":
        lines = [f"# frame {frame}", "# timestamp tx ty tz qx qy qz qw"]
        for stamp, M in zip(stamps, T, strict=True):
            row = transform_to_tum(M)
            lines.append(f"{stamp:.6f} " + " ".join(f"{v:.9g}" for v in row))
        return PlainTextResponse("\n".join(lines) + "\n")
    return TrajectoryOut(robot_id=robot_id, frame=frame,
                         poses=[_pose(stamp, M) for stamp, M in zip(stamps, T, strict=True)])
