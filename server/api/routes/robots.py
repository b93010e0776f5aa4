"""``GET /v1/robots`` and ``GET /v1/robots/{robot_id}/trajectory``: robots and their camera paths."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import PlainTextResponse

from wardmap.server.api.deps import StoreDep
from wardmap.server.api.schemas import ErrorOut, PoseOut, RobotList, RobotOut, TrajectoryOut
from wardmap.shared.se3 import transform_to_tum

router = APIRouter()


@router.get("/v1/robots", response_model=RobotList)
def robots(store: StoreDep) -> RobotList:
    return RobotList(robots=[
        RobotOut(robot_id=r.robot_id, keyframes=r.keyframes, sessions=r.sessions,
                 first_seen_s=r.first_seen_s, last_seen_s=r.last_seen_s)
        for r in store.robots()
    ])


@router.get(
    "/v1/robots/{robot_id}/trajectory",
    response_model=None,
    responses={200: {"model": TrajectoryOut}, 404: {"model": ErrorOut}},
)
def trajectory(
    store: StoreDep,
    robot_id: str,
    format: Annotated[Literal["tum", "json"], Query()] = "json",
) -> Any:
    stamps, T = store.trajectory(robot_id)
    if len(stamps) == 0:
        raise HTTPException(404, f"unknown robot {robot_id!r}")
    if format == "tum":
        lines = ["# timestamp tx ty tz qx qy qz qw"]
        for stamp, M in zip(stamps, T, strict=True):
            row = transform_to_tum(M)
            lines.append(f"{stamp:.6f} " + " ".join(f"{v:.9g}" for v in row))
        return PlainTextResponse("\n".join(lines) + "\n")
    poses = []
    for stamp, M in zip(stamps, T, strict=True):
        row = transform_to_tum(M)
        poses.append(PoseOut(stamp=float(stamp), t=[float(v) for v in row[:3]],
                             q_xyzw=[float(v) for v in row[3:]]))
    return TrajectoryOut(robot_id=robot_id, poses=poses)
