from egoslam_client.messages import geometry_pb2 as _geometry_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Iterable as _Iterable, Mapping as _Mapping, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor
SERVICE_STATE_FAILED: ServiceState
SERVICE_STATE_FINISHED: ServiceState
SERVICE_STATE_RUNNING: ServiceState
SERVICE_STATE_STARTING: ServiceState
SERVICE_STATE_UNSPECIFIED: ServiceState

class MapPoint(_message.Message):
    __slots__ = ["largest_reprojection_sigmas", "observations", "position", "relative_std", "track_id"]
    LARGEST_REPROJECTION_SIGMAS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    RELATIVE_STD_FIELD_NUMBER: _ClassVar[int]
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    largest_reprojection_sigmas: float
    observations: int
    position: _geometry_pb2.Vec3
    relative_std: float
    track_id: int
    def __init__(self, track_id: _Optional[int] = ..., position: _Optional[_Union[_geometry_pb2.Vec3, _Mapping]] = ..., observations: _Optional[int] = ..., relative_std: _Optional[float] = ..., largest_reprojection_sigmas: _Optional[float] = ...) -> None: ...

class MapPoints(_message.Message):
    __slots__ = ["points"]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    points: _containers.RepeatedCompositeFieldContainer[MapPoint]
    def __init__(self, points: _Optional[_Iterable[_Union[MapPoint, _Mapping]]] = ...) -> None: ...

class Snapshot(_message.Message):
    __slots__ = ["frames", "keyframes", "map", "status"]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    MAP_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    frames: Trajectory
    keyframes: Trajectory
    map: MapPoints
    status: Status
    def __init__(self, keyframes: _Optional[_Union[Trajectory, _Mapping]] = ..., frames: _Optional[_Union[Trajectory, _Mapping]] = ..., map: _Optional[_Union[MapPoints, _Mapping]] = ..., status: _Optional[_Union[Status, _Mapping]] = ...) -> None: ...

class Status(_message.Message):
    __slots__ = ["frames", "keyframes", "message", "run_id", "service", "state", "windows"]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    RUN_ID_FIELD_NUMBER: _ClassVar[int]
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    WINDOWS_FIELD_NUMBER: _ClassVar[int]
    frames: int
    keyframes: int
    message: str
    run_id: str
    service: str
    state: ServiceState
    windows: int
    def __init__(self, service: _Optional[str] = ..., state: _Optional[_Union[ServiceState, str]] = ..., frames: _Optional[int] = ..., keyframes: _Optional[int] = ..., windows: _Optional[int] = ..., message: _Optional[str] = ..., run_id: _Optional[str] = ...) -> None: ...

class Trajectory(_message.Message):
    __slots__ = ["poses"]
    POSES_FIELD_NUMBER: _ClassVar[int]
    poses: _containers.RepeatedCompositeFieldContainer[_geometry_pb2.Pose]
    def __init__(self, poses: _Optional[_Iterable[_Union[_geometry_pb2.Pose, _Mapping]]] = ...) -> None: ...

class ServiceState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = []
