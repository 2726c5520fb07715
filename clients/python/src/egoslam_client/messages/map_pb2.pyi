from egoslam_client.messages import geometry_pb2 as _geometry_pb2
from egoslam_client.messages import frontend_pb2 as _frontend_pb2
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
SOLVE_STATUS_FAILED: SolveStatus
SOLVE_STATUS_PASS_THROUGH: SolveStatus
SOLVE_STATUS_SOLVED: SolveStatus
SOLVE_STATUS_UNSPECIFIED: SolveStatus

class KeyframeFeatures(_message.Message):
    __slots__ = ["descriptors", "keyframe_id", "patch_track_ids", "patches", "track_ids", "x", "y"]
    DESCRIPTORS_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    PATCHES_FIELD_NUMBER: _ClassVar[int]
    PATCH_TRACK_IDS_FIELD_NUMBER: _ClassVar[int]
    TRACK_IDS_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    descriptors: bytes
    keyframe_id: int
    patch_track_ids: _containers.RepeatedScalarFieldContainer[int]
    patches: bytes
    track_ids: _containers.RepeatedScalarFieldContainer[int]
    x: _containers.RepeatedScalarFieldContainer[float]
    y: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, keyframe_id: _Optional[int] = ..., track_ids: _Optional[_Iterable[int]] = ..., descriptors: _Optional[bytes] = ..., x: _Optional[_Iterable[float]] = ..., y: _Optional[_Iterable[float]] = ..., patch_track_ids: _Optional[_Iterable[int]] = ..., patches: _Optional[bytes] = ...) -> None: ...

class KeyframePose(_message.Message):
    __slots__ = ["keyframe_id", "pose"]
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    keyframe_id: int
    pose: _geometry_pb2.Pose
    def __init__(self, keyframe_id: _Optional[int] = ..., pose: _Optional[_Union[_geometry_pb2.Pose, _Mapping]] = ...) -> None: ...

class KeyframeStamp(_message.Message):
    __slots__ = ["frame_id", "frames_since_previous", "frames_since_previous_ids", "frames_since_previous_timestamps_s", "keyframe_id", "timestamp_s"]
    FRAMES_SINCE_PREVIOUS_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SINCE_PREVIOUS_IDS_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SINCE_PREVIOUS_TIMESTAMPS_S_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_S_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    frames_since_previous: _containers.RepeatedCompositeFieldContainer[_frontend_pb2.FrameStamp]
    frames_since_previous_ids: _containers.RepeatedScalarFieldContainer[int]
    frames_since_previous_timestamps_s: _containers.RepeatedScalarFieldContainer[float]
    keyframe_id: int
    timestamp_s: float
    def __init__(self, keyframe_id: _Optional[int] = ..., frame_id: _Optional[int] = ..., timestamp_s: _Optional[float] = ..., frames_since_previous_ids: _Optional[_Iterable[int]] = ..., frames_since_previous_timestamps_s: _Optional[_Iterable[float]] = ..., frames_since_previous: _Optional[_Iterable[_Union[_frontend_pb2.FrameStamp, _Mapping]]] = ...) -> None: ...

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

class Observation(_message.Message):
    __slots__ = ["keyframe_id", "track_id", "x", "y"]
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    keyframe_id: int
    track_id: int
    x: float
    y: float
    def __init__(self, keyframe_id: _Optional[int] = ..., track_id: _Optional[int] = ..., x: _Optional[float] = ..., y: _Optional[float] = ...) -> None: ...

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

class SolutionQuality(_message.Message):
    __slots__ = ["inlier_observations", "outlier_observations", "reason", "reprojection_rmse_px", "status"]
    INLIER_OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    OUTLIER_OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    REPROJECTION_RMSE_PX_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    inlier_observations: int
    outlier_observations: int
    reason: str
    reprojection_rmse_px: float
    status: SolveStatus
    def __init__(self, status: _Optional[_Union[SolveStatus, str]] = ..., reason: _Optional[str] = ..., reprojection_rmse_px: _Optional[float] = ..., inlier_observations: _Optional[int] = ..., outlier_observations: _Optional[int] = ...) -> None: ...

class StageTiming(_message.Message):
    __slots__ = ["milliseconds", "stage"]
    MILLISECONDS_FIELD_NUMBER: _ClassVar[int]
    STAGE_FIELD_NUMBER: _ClassVar[int]
    milliseconds: float
    stage: str
    def __init__(self, stage: _Optional[str] = ..., milliseconds: _Optional[float] = ...) -> None: ...

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

class WindowSolution(_message.Message):
    __slots__ = ["end_of_stream", "intrinsics", "keyframe_features", "keyframe_ids", "keyframes", "observations", "overlap", "points", "poses", "quality", "stream_id", "timings", "trailing_frames", "weak_observations", "window_id"]
    END_OF_STREAM_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_FEATURES_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_IDS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    OVERLAP_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    STREAM_ID_FIELD_NUMBER: _ClassVar[int]
    TIMINGS_FIELD_NUMBER: _ClassVar[int]
    TRAILING_FRAMES_FIELD_NUMBER: _ClassVar[int]
    WEAK_OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    WINDOW_ID_FIELD_NUMBER: _ClassVar[int]
    end_of_stream: bool
    intrinsics: _geometry_pb2.Intrinsics
    keyframe_features: _containers.RepeatedCompositeFieldContainer[KeyframeFeatures]
    keyframe_ids: _containers.RepeatedScalarFieldContainer[int]
    keyframes: _containers.RepeatedCompositeFieldContainer[KeyframeStamp]
    observations: _containers.RepeatedCompositeFieldContainer[Observation]
    overlap: int
    points: _containers.RepeatedCompositeFieldContainer[MapPoint]
    poses: _containers.RepeatedCompositeFieldContainer[KeyframePose]
    quality: SolutionQuality
    stream_id: int
    timings: _containers.RepeatedCompositeFieldContainer[StageTiming]
    trailing_frames: _containers.RepeatedCompositeFieldContainer[_frontend_pb2.FrameStamp]
    weak_observations: _containers.RepeatedCompositeFieldContainer[Observation]
    window_id: int
    def __init__(self, window_id: _Optional[int] = ..., keyframe_ids: _Optional[_Iterable[int]] = ..., overlap: _Optional[int] = ..., poses: _Optional[_Iterable[_Union[KeyframePose, _Mapping]]] = ..., points: _Optional[_Iterable[_Union[MapPoint, _Mapping]]] = ..., observations: _Optional[_Iterable[_Union[Observation, _Mapping]]] = ..., quality: _Optional[_Union[SolutionQuality, _Mapping]] = ..., timings: _Optional[_Iterable[_Union[StageTiming, _Mapping]]] = ..., keyframes: _Optional[_Iterable[_Union[KeyframeStamp, _Mapping]]] = ..., end_of_stream: bool = ..., trailing_frames: _Optional[_Iterable[_Union[_frontend_pb2.FrameStamp, _Mapping]]] = ..., intrinsics: _Optional[_Union[_geometry_pb2.Intrinsics, _Mapping]] = ..., stream_id: _Optional[int] = ..., weak_observations: _Optional[_Iterable[_Union[Observation, _Mapping]]] = ..., keyframe_features: _Optional[_Iterable[_Union[KeyframeFeatures, _Mapping]]] = ...) -> None: ...

class SolveStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = []

class ServiceState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = []
