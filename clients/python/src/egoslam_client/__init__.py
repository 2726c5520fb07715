"""Python client of egoslam: follow a running egoslam's poses, trajectory, map and status
over zenoh (key expressions and messages: docs/egress.md).

    from egoslam_client import Client

    with Client("tcp/127.0.0.1:7447", device="default") as client:
        client.on_pose(lambda pose: print(pose.frame_id, pose.position))
        client.wait_finished(timeout=600)
        snapshot = client.snapshot()
"""
from egoslam_client.client import Client, TlsFiles
from egoslam_client.messages.geometry_pb2 import Pose, Quaternion, Vec3
from egoslam_client.messages.map_pb2 import (
    MapPoint,
    MapPoints,
    ServiceState,
    Snapshot,
    Status,
    Trajectory,
)

__all__ = [
    "Client",
    "TlsFiles",
    "MapPoint",
    "MapPoints",
    "Pose",
    "Quaternion",
    "ServiceState",
    "Snapshot",
    "Status",
    "Trajectory",
    "Vec3",
]
