"""A zenoh session following one egoslam device: typed callbacks per key, the snapshot
queryable, and the end of the stream."""
from __future__ import annotations

import dataclasses
import json
import pathlib
import sys
import threading
import time
from typing import Callable, List, Optional, TypeVar

import zenoh
from google.protobuf.message import DecodeError, Message

from egoslam_client.messages import geometry_pb2, map_pb2

M = TypeVar("M", bound=Message)


@dataclasses.dataclass(frozen=True)
class TlsFiles:
    """PEM files for a tls/ endpoint: root_ca verifies the merger's certificate;
    certificate and private_key are this client's, for a mutual-TLS merger."""

    root_ca: Optional[pathlib.Path] = None
    certificate: Optional[pathlib.Path] = None
    private_key: Optional[pathlib.Path] = None


def _config(endpoint: str, tls: TlsFiles) -> zenoh.Config:
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
    return config


class Client:
    """Follows `egoslam/<device>/*` at `endpoint` (the merger's `--zenoh-listen`).

    Connecting retries until the merger listens, for at most `timeout` seconds; a
    ConnectionError says why it gave up. Malformed messages are counted in `rejected`
    and reported on stderr, never raised."""

    def __init__(self, endpoint: str = "tcp/127.0.0.1:7447", device: str = "default",
                 timeout: float = 60.0, tls: TlsFiles = TlsFiles()) -> None:
        self.prefix = f"egoslam/{device}"
        self.rejected = 0
        self._finished = threading.Event()
        self._subscribers: List[zenoh.Subscriber] = []
        self._session = self._open(endpoint, timeout, tls)
        self._watch(f"{self.prefix}/status", map_pb2.Status, self._on_status)

    @staticmethod
    def _open(endpoint: str, timeout: float, tls: TlsFiles) -> zenoh.Session:
        deadline = time.monotonic() + timeout
        while True:
            try:
                session = zenoh.open(_config(endpoint, tls))
                for _ in range(20):
                    if list(session.info.peers_zid()):
                        return session
                    time.sleep(0.05)
                session.close()
            except Exception as e:  # zenoh raises its own error type for a refused link
                if time.monotonic() > deadline:
                    raise ConnectionError(f"cannot reach {endpoint}: {e}") from e
            if time.monotonic() > deadline:
                raise ConnectionError(f"no egoslam merger at {endpoint} after {timeout} s")
            time.sleep(0.2)

    def _decode(self, kind: type[M], payload: bytes) -> Optional[M]:
        try:
            return kind.FromString(payload)
        except DecodeError as e:
            self.rejected += 1
            print(f"malformed {kind.__name__} message: {e}", file=sys.stderr)
            return None

    def _watch(self, key: str, kind: type[M], callback: Callable[[M], None]) -> None:
        def on_sample(sample: zenoh.Sample) -> None:
            message = self._decode(kind, sample.payload.to_bytes())
            if message is not None:
                callback(message)

        self._subscribers.append(self._session.declare_subscriber(key, on_sample))

    def _on_status(self, status: map_pb2.Status) -> None:
        if status.service == "merger" and status.state == map_pb2.SERVICE_STATE_FINISHED:
            self._finished.set()

    def on_pose(self, callback: Callable[[geometry_pb2.Pose], None]) -> None:
        """Every frame's pose when new (revision 0) or changed (revision + 1)."""
        self._watch(f"{self.prefix}/pose", geometry_pb2.Pose, callback)

    def on_trajectory(self, callback: Callable[[map_pb2.Trajectory], None]) -> None:
        """All keyframe poses, after every window."""
        self._watch(f"{self.prefix}/trajectory", map_pb2.Trajectory, callback)

    def on_map(self, callback: Callable[[map_pb2.MapPoints], None]) -> None:
        """The points of the latest window, in chunks."""
        self._watch(f"{self.prefix}/map", map_pb2.MapPoints, callback)

    def on_status(self, callback: Callable[[map_pb2.Status], None]) -> None:
        """Each service status (RUNNING after every window, FINISHED at the end)."""
        self._watch(f"{self.prefix}/status", map_pb2.Status, callback)

    def snapshot(self) -> Optional[map_pb2.Snapshot]:
        """Everything so far: keyframes, every posed frame, all points, the status."""
        for reply in self._session.get(f"{self.prefix}/snapshot"):
            if reply.ok is not None:
                return self._decode(map_pb2.Snapshot, reply.ok.payload.to_bytes())
        return None

    def wait_finished(self, timeout: Optional[float] = None) -> bool:
        """Waits for the merger's FINISHED status; whether it came."""
        return self._finished.wait(timeout)

    def close(self) -> None:
        for s in self._subscribers:
            s.undeclare()
        self._subscribers.clear()
        self._session.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
