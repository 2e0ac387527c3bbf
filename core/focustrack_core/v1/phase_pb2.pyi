from focustrack_core.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class PhaseResult(_message.Message):
    __slots__ = ("instrument", "slide", "row", "col", "sequence", "nonce", "reference_z_um", "pixel_size_um", "stage_x_um", "stage_y_um", "shape", "dtype", "compute_time_s", "error", "tag", "background_share")
    INSTRUMENT_FIELD_NUMBER: _ClassVar[int]
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    NONCE_FIELD_NUMBER: _ClassVar[int]
    REFERENCE_Z_UM_FIELD_NUMBER: _ClassVar[int]
    PIXEL_SIZE_UM_FIELD_NUMBER: _ClassVar[int]
    STAGE_X_UM_FIELD_NUMBER: _ClassVar[int]
    STAGE_Y_UM_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    COMPUTE_TIME_S_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    TAG_FIELD_NUMBER: _ClassVar[int]
    BACKGROUND_SHARE_FIELD_NUMBER: _ClassVar[int]
    instrument: str
    slide: str
    row: int
    col: int
    sequence: int
    nonce: bytes
    reference_z_um: float
    pixel_size_um: float
    stage_x_um: float
    stage_y_um: float
    shape: _containers.RepeatedScalarFieldContainer[int]
    dtype: str
    compute_time_s: float
    error: _common_pb2.Error
    tag: bytes
    background_share: float
    def __init__(self, instrument: _Optional[str] = ..., slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ..., sequence: _Optional[int] = ..., nonce: _Optional[bytes] = ..., reference_z_um: _Optional[float] = ..., pixel_size_um: _Optional[float] = ..., stage_x_um: _Optional[float] = ..., stage_y_um: _Optional[float] = ..., shape: _Optional[_Iterable[int]] = ..., dtype: _Optional[str] = ..., compute_time_s: _Optional[float] = ..., error: _Optional[_Union[_common_pb2.Error, _Mapping]] = ..., tag: _Optional[bytes] = ..., background_share: _Optional[float] = ...) -> None: ...
