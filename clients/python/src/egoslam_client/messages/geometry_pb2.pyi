from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Iterable as _Iterable, Mapping as _Mapping, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor
LENS_MODEL_DOUBLE_SPHERE: LensModel
LENS_MODEL_EQUIDISTANT: LensModel
LENS_MODEL_RADIAL_TANGENTIAL: LensModel
TRACKING_STATE_LOST: TrackingState
TRACKING_STATE_PREDICTED: TrackingState
TRACKING_STATE_REFINED: TrackingState
TRACKING_STATE_ROTATION: TrackingState
TRACKING_STATE_TRACKING: TrackingState
TRACKING_STATE_UNSPECIFIED: TrackingState

class Intrinsics(_message.Message):
    __slots__ = ["cx", "cy", "distortion", "fx", "fy", "height", "lens", "width"]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    DISTORTION_FIELD_NUMBER: _ClassVar[int]
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    LENS_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    cx: float
    cy: float
    distortion: _containers.RepeatedScalarFieldContainer[float]
    fx: float
    fy: float
    height: int
    lens: LensModel
    width: int
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., distortion: _Optional[_Iterable[float]] = ..., lens: _Optional[_Union[LensModel, str]] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ["frame_id", "inliers", "interpolated", "orientation", "position", "revision", "segment_id", "timestamp_s", "tracking"]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    INTERPOLATED_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    REVISION_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_S_FIELD_NUMBER: _ClassVar[int]
    TRACKING_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    inliers: int
    interpolated: bool
    orientation: Quaternion
    position: Vec3
    revision: int
    segment_id: int
    timestamp_s: float
    tracking: TrackingState
    def __init__(self, frame_id: _Optional[int] = ..., timestamp_s: _Optional[float] = ..., position: _Optional[_Union[Vec3, _Mapping]] = ..., orientation: _Optional[_Union[Quaternion, _Mapping]] = ..., segment_id: _Optional[int] = ..., revision: _Optional[int] = ..., interpolated: bool = ..., tracking: _Optional[_Union[TrackingState, str]] = ..., inliers: _Optional[int] = ...) -> None: ...

class Quaternion(_message.Message):
    __slots__ = ["w", "x", "y", "z"]
    W_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    w: float
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., w: _Optional[float] = ...) -> None: ...

class Vec3(_message.Message):
    __slots__ = ["x", "y", "z"]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class TrackingState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = []

class LensModel(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = []
