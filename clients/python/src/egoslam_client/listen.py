"""egoslam-listen: prints an egoslam device's poses as they arrive and saves the
trajectory (the latest revision of every frame) as a TUM file.

    egoslam-listen --connect tcp/127.0.0.1:7447 --device default --out trajectory.tum --until-finished
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import threading
import time
from typing import Dict, List, Optional

from egoslam_client.client import Client, TlsFiles
from egoslam_client.messages import geometry_pb2, map_pb2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="egoslam-listen", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447",
                        help="the merger's zenoh endpoint (default: %(default)s)")
    parser.add_argument("--device", default="default")
    parser.add_argument("--out", type=pathlib.Path, help="TUM file to write")
    parser.add_argument("--until-finished", action="store_true",
                        help="exit when the merger reports the stream finished")
    parser.add_argument("--timeout", type=float, default=60.0,
                        help="seconds to wait for the merger (and, with --until-finished, for the end)")
    parser.add_argument("--quiet", action="store_true", help="do not print every pose")
    parser.add_argument("--tls-root-ca", type=pathlib.Path,
                        help="CA certificate (PEM) that signed the merger's certificate")
    parser.add_argument("--tls-certificate", type=pathlib.Path,
                        help="this client's certificate (PEM), for a mutual-TLS merger")
    parser.add_argument("--tls-private-key", type=pathlib.Path,
                        help="the private key of --tls-certificate (PEM)")
    return parser


def _write_tum(path: pathlib.Path, poses: List[geometry_pb2.Pose]) -> None:
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (world_from_camera)\n")
        for p in sorted(poses, key=lambda p: p.timestamp_s):
            t, q = p.position, p.orientation
            f.write(f"{p.timestamp_s:.6f} {t.x:.6f} {t.y:.6f} {t.z:.6f} "
                    f"{q.x:.6f} {q.y:.6f} {q.z:.6f} {q.w:.6f}\n")


def main(argv: Optional[List[str]] = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if bool(args.tls_certificate) != bool(args.tls_private_key):
        parser.error("--tls-certificate and --tls-private-key go together")
    for path in (args.tls_root_ca, args.tls_certificate, args.tls_private_key):
        if path and not path.is_file():
            parser.error(f"{path}: no such file")
    tls = TlsFiles(args.tls_root_ca, args.tls_certificate, args.tls_private_key)

    poses: Dict[int, geometry_pb2.Pose] = {}
    lock = threading.Lock()
    counts = {"pose": 0, "trajectory": 0, "map": 0, "status": 0}

    def keep(pose: geometry_pb2.Pose) -> None:
        old = poses.get(pose.frame_id)
        if old is None or pose.revision >= old.revision:
            poses[pose.frame_id] = pose

    def on_pose(pose: geometry_pb2.Pose) -> None:
        with lock:
            counts["pose"] += 1
            keep(pose)
        if not args.quiet:
            p, q = pose.position, pose.orientation
            print(f"frame {pose.frame_id} t={pose.timestamp_s:.6f} rev {pose.revision} "
                  f"pos {p.x:.4f} {p.y:.4f} {p.z:.4f} "
                  f"q {q.x:.4f} {q.y:.4f} {q.z:.4f} {q.w:.4f}"
                  f"{' (interpolated)' if pose.interpolated else ''}")

    def on_status(status: map_pb2.Status) -> None:
        counts["status"] += 1
        print(f"status {status.service}: {map_pb2.ServiceState.Name(status.state)}, "
              f"{status.keyframes} keyframes, {status.windows} windows; {status.message}",
              file=sys.stderr)

    def on_trajectory(_: map_pb2.Trajectory) -> None:
        counts["trajectory"] += 1

    def on_map(points: map_pb2.MapPoints) -> None:
        counts["map"] += len(points.points)

    def fetch_snapshot(client: Client) -> None:
        snapshot = client.snapshot()
        if snapshot is None:
            return
        with lock:
            for pose in snapshot.frames.poses:
                keep(pose)
        print(f"snapshot: {len(snapshot.frames.poses)} frames, "
              f"{len(snapshot.map.points)} map points", file=sys.stderr)

    try:
        client = Client(args.connect, args.device, args.timeout, tls)
    except ConnectionError as e:
        print(e, file=sys.stderr)
        return 1
    code = 0
    try:
        client.on_pose(on_pose)
        client.on_status(on_status)
        client.on_trajectory(on_trajectory)
        client.on_map(on_map)
        # A late joiner gets everything so far from the snapshot queryable.
        fetch_snapshot(client)
        if args.until_finished:
            if not client.wait_finished(args.timeout):
                print("the merger did not finish in time", file=sys.stderr)
                code = 1
            else:
                # The publishers drop rather than block the pipeline on a slow link: the
                # final snapshot fills any such gap.
                fetch_snapshot(client)
        else:
            while True:
                time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        client.close()
        if args.out:
            with lock:
                _write_tum(args.out, list(poses.values()))
        print(f"received {counts['pose']} pose, {counts['trajectory']} trajectory, "
              f"{counts['map']} map point, {counts['status']} status messages "
              f"({client.rejected} malformed); {len(poses)} frames", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
