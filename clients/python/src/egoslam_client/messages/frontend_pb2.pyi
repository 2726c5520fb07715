from egoslam_client.messages import geometry_pb2 as _geometry_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Iterable as _Iterable, Mapping as _Mapping, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor
KEYFRAME_REASON_FIRST: KeyframeReason
KEYFRAME_REASON_FLOW: KeyframeReason
KEYFRAME_REASON_FRAME_COUNT: KeyframeReason
KEYFRAME_REASON_LAST: KeyframeReason
KEYFRAME_REASON_TRACK_LOSS: KeyframeReason
KEYFRAME_REASON_UNSPECIFIED: KeyframeReason

class FrameHeader(_message.Message):
    __slots__ = ["frame_id", "height", "source", "timestamp_s", "width"]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_S_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    height: int
    source: str
    timestamp_s: float
    width: int
    def __init__(self, frame_id: _Optional[int] = ..., timestamp_s: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., source: _Optional[str] = ...) -> None: ...

class FrameStamp(_message.Message):
    __slots__ = ["frame_id", "timestamp_s", "tracks"]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_S_FIELD_NUMBER: _ClassVar[int]
    TRACKS_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    timestamp_s: float
    tracks: _containers.RepeatedCompositeFieldContainer[TrackObservation]
    def __init__(self, frame_id: _Optional[int] = ..., timestamp_s: _Optional[float] = ..., tracks: _Optional[_Iterable[_Union[TrackObservation, _Mapping]]] = ...) -> None: ...

class Keyframe(_message.Message):
    __slots__ = ["end_of_stream", "frame_id", "frames_since_previous", "intrinsics", "keyframe_id", "mean_flow_px", "reason", "timestamp_s", "tracks", "trailing_frames"]
    END_OF_STREAM_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SINCE_PREVIOUS_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    MEAN_FLOW_PX_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_S_FIELD_NUMBER: _ClassVar[int]
    TRACKS_FIELD_NUMBER: _ClassVar[int]
    TRAILING_FRAMES_FIELD_NUMBER: _ClassVar[int]
    end_of_stream: bool
    frame_id: int
    frames_since_previous: _containers.RepeatedCompositeFieldContainer[FrameStamp]
    intrinsics: _geometry_pb2.Intrinsics
    keyframe_id: int
    mean_flow_px: float
    reason: KeyframeReason
    timestamp_s: float
    tracks: _containers.RepeatedCompositeFieldContainer[TrackObservation]
    trailing_frames: _containers.RepeatedCompositeFieldContainer[FrameStamp]
    def __init__(self, keyframe_id: _Optional[int] = ..., frame_id: _Optional[int] = ..., timestamp_s: _Optional[float] = ..., intrinsics: _Optional[_Union[_geometry_pb2.Intrinsics, _Mapping]] = ..., tracks: _Optional[_Iterable[_Union[TrackObservation, _Mapping]]] = ..., frames_since_previous: _Optional[_Iterable[_Union[FrameStamp, _Mapping]]] = ..., mean_flow_px: _Optional[float] = ..., reason: _Optional[_Union[KeyframeReason, str]] = ..., end_of_stream: bool = ..., trailing_frames: _Optional[_Iterable[_Union[FrameStamp, _Mapping]]] = ...) -> None: ...

class LiveFrame(_message.Message):
    __slots__ = ["captured_unix_ns", "first_of_stream", "frame_id", "intrinsics", "timestamp_s", "tracks"]
    CAPTURED_UNIX_NS_FIELD_NUMBER: _ClassVar[int]
    FIRST_OF_STREAM_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_S_FIELD_NUMBER: _ClassVar[int]
    TRACKS_FIELD_NUMBER: _ClassVar[int]
    captured_unix_ns: int
    first_of_stream: bool
    frame_id: int
    intrinsics: _geometry_pb2.Intrinsics
    timestamp_s: float
    tracks: _containers.RepeatedCompositeFieldContainer[TrackObservation]
    def __init__(self, frame_id: _Optional[int] = ..., timestamp_s: _Optional[float] = ..., captured_unix_ns: _Optional[int] = ..., tracks: _Optional[_Iterable[_Union[TrackObservation, _Mapping]]] = ..., intrinsics: _Optional[_Union[_geometry_pb2.Intrinsics, _Mapping]] = ..., first_of_stream: bool = ...) -> None: ...

class TrackObservation(_message.Message):
    __slots__ = ["descriptor", "patch", "raw_x", "raw_y", "track_id", "x", "y"]
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    PATCH_FIELD_NUMBER: _ClassVar[int]
    RAW_X_FIELD_NUMBER: _ClassVar[int]
    RAW_Y_FIELD_NUMBER: _ClassVar[int]
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    descriptor: bytes
    patch: bytes
    raw_x: float
    raw_y: float
    track_id: int
    x: float
    y: float
    def __init__(self, track_id: _Optional[int] = ..., raw_x: _Optional[float] = ..., raw_y: _Optional[float] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., descriptor: _Optional[bytes] = ..., patch: _Optional[bytes] = ...) -> None: ...

class KeyframeReason(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = []
