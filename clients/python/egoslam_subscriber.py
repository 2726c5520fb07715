#!/usr/bin/env python3
"""Subscribes to an egoslam device over zenoh, prints poses as they arrive and saves the
trajectory (latest revision of every frame) as a TUM file.

    python3 clients/python/egoslam_subscriber.py --connect tcp/127.0.0.1:7447 \
        --device default --out trajectory.tum [--until-finished]

The message classes are generated from proto/egoslam/v1/*.proto with protoc at start (into
a temporary folder), so the client always matches the .proto files it ships with.
Requirements: clients/python/requirements.txt. Key expressions: docs/egress.md.
"""

import argparse
import json
import pathlib
import shutil
import subprocess
import sys
import tempfile
import threading
import time

REPO = pathlib.Path(__file__).resolve().parents[2]


def generated_modules():
    """Runs protoc on proto/ and imports the generated egoslam.v1 modules.

    The temporary folder is removed once they are imported (they are then in memory), so
    repeated runs leave nothing behind, even when this process is killed later."""
    out = pathlib.Path(tempfile.mkdtemp(prefix="egoslam_pb_"))
    try:
        protos = sorted((REPO / "proto" / "egoslam" / "v1").glob("*.proto"))
        subprocess.run(
            ["protoc", f"-I{REPO / 'proto'}", f"--python_out={out}", *map(str, protos)],
            check=True,
        )
        sys.path.insert(0, str(out))
        from egoslam.v1 import geometry_pb2, map_pb2  # noqa: E402  (generated above)
    finally:
        if str(out) in sys.path:
            sys.path.remove(str(out))
        shutil.rmtree(out, ignore_errors=True)

    class Messages:
        Pose = geometry_pb2.Pose
        Status = map_pb2.Status
        Snapshot = map_pb2.Snapshot
        ServiceState = map_pb2.ServiceState
        SERVICE_STATE_FINISHED = map_pb2.SERVICE_STATE_FINISHED

    return Messages


def open_session(zenoh, endpoint, timeout_s, tls):
    """Opens a peer session connected to the merger's endpoint, retrying until it listens.

    `tls` holds the PEM paths for a tls/ endpoint: root_ca verifies the merger's
    certificate; certificate and private_key are this client's, for mutual TLS."""
    deadline = time.monotonic() + timeout_s
    while True:
        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))
        config.insert_json5("listen/endpoints", "[]")
        config.insert_json5("scouting/multicast/enabled", "false")
        base = "transport/link/tls"
        if tls.root_ca:
            config.insert_json5(f"{base}/root_ca_certificate", json.dumps(str(tls.root_ca)))
        if tls.certificate and tls.private_key:
            config.insert_json5(f"{base}/connect_certificate", json.dumps(str(tls.certificate)))
            config.insert_json5(f"{base}/connect_private_key", json.dumps(str(tls.private_key)))
            config.insert_json5(f"{base}/enable_mtls", "true")
        try:
            session = zenoh.open(config)
            for _ in range(20):
                if list(session.info.peers_zid()):
                    return session
                time.sleep(0.05)
            session.close()
        except Exception as e:  # zenoh raises its own error type for a refused connection
            if time.monotonic() > deadline:
                raise SystemExit(f"cannot reach {endpoint}: {e}")
        if time.monotonic() > deadline:
            raise SystemExit(f"no egoslam merger at {endpoint} after {timeout_s} s")
        time.sleep(0.2)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447")
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
    args = parser.parse_args()
    if bool(args.tls_certificate) != bool(args.tls_private_key):
        parser.error("--tls-certificate and --tls-private-key go together")
    for path in (args.tls_root_ca, args.tls_certificate, args.tls_private_key):
        if path and not path.is_file():
            parser.error(f"{path}: no such file")
    tls = argparse.Namespace(root_ca=args.tls_root_ca, certificate=args.tls_certificate,
                             private_key=args.tls_private_key)

    import zenoh
    from google.protobuf.message import DecodeError

    pb = generated_modules()
    prefix = f"egoslam/{args.device}"
    poses = {}  # frame_id -> latest Pose
    lock = threading.Lock()
    finished = threading.Event()
    counts = {"pose": 0, "trajectory": 0, "status": 0, "rejected": 0}

    def keep(pose):
        old = poses.get(pose.frame_id)
        if old is None or pose.revision >= old.revision:
            poses[pose.frame_id] = pose

    def on_pose(sample):
        try:
            pose = pb.Pose.FromString(sample.payload.to_bytes())
        except DecodeError as e:  # a malformed message is reported, never fatal
            counts["rejected"] += 1
            print(f"malformed pose message: {e}", file=sys.stderr)
            return
        with lock:
            counts["pose"] += 1
            keep(pose)
        if not args.quiet:
            p, q = pose.position, pose.orientation
            print(f"frame {pose.frame_id} t={pose.timestamp_s:.6f} rev {pose.revision} "
                  f"pos {p.x:.4f} {p.y:.4f} {p.z:.4f} "
                  f"q {q.x:.4f} {q.y:.4f} {q.z:.4f} {q.w:.4f}"
                  f"{' (interpolated)' if pose.interpolated else ''}")

    def on_status(sample):
        try:
            status = pb.Status.FromString(sample.payload.to_bytes())
        except DecodeError as e:
            counts["rejected"] += 1
            print(f"malformed status message: {e}", file=sys.stderr)
            return
        counts["status"] += 1
        print(f"status {status.service}: {pb.ServiceState.Name(status.state)}, "
              f"{status.keyframes} keyframes, {status.windows} windows; {status.message}",
              file=sys.stderr)
        if status.service == "merger" and status.state == pb.SERVICE_STATE_FINISHED:
            finished.set()

    def on_trajectory(sample):
        counts["trajectory"] += 1

    session = open_session(zenoh, args.connect, args.timeout, tls)
    subscribers = [
        session.declare_subscriber(f"{prefix}/pose", on_pose),
        session.declare_subscriber(f"{prefix}/status", on_status),
        session.declare_subscriber(f"{prefix}/trajectory", on_trajectory),
    ]
    def fetch_snapshot():
        for reply in session.get(f"{prefix}/snapshot"):
            if reply.ok is None:
                continue
            snapshot = pb.Snapshot.FromString(reply.ok.payload.to_bytes())
            with lock:
                for pose in snapshot.frames.poses:
                    keep(pose)
            print(f"snapshot: {len(snapshot.frames.poses)} frames, "
                  f"{len(snapshot.map.points)} map points", file=sys.stderr)

    # A late joiner gets everything so far from the snapshot queryable.
    fetch_snapshot()

    try:
        if args.until_finished:
            if not finished.wait(args.timeout):
                raise SystemExit("the merger did not finish in time")
            # The publishers drop rather than block the pipeline on a slow link: the final
            # snapshot fills any such gap.
            fetch_snapshot()
        else:
            while True:
                time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        for s in subscribers:
            s.undeclare()
        session.close()
        if args.out:
            with lock:
                ordered = sorted(poses.values(), key=lambda p: p.timestamp_s)
            with open(args.out, "w") as f:
                f.write("# timestamp tx ty tz qx qy qz qw (world_from_camera)\n")
                for p in ordered:
                    t, q = p.position, p.orientation
                    f.write(f"{p.timestamp_s:.6f} {t.x:.6f} {t.y:.6f} {t.z:.6f} "
                            f"{q.x:.6f} {q.y:.6f} {q.z:.6f} {q.w:.6f}\n")
        print(f"received {counts['pose']} pose, {counts['trajectory']} trajectory, "
              f"{counts['status']} status messages ({counts['rejected']} malformed); "
              f"{len(poses)} frames", file=sys.stderr)


if __name__ == "__main__":
    main()
