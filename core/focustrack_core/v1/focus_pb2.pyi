from focustrack_core.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class FocusResult(_message.Message):
    __slots__ = ("slide", "row", "col", "sequence", "metric", "z_um", "scores", "best_z_um", "sigma_um", "flags", "compute_time_s", "error", "instrument", "runner_up_z_um", "chosen_probability", "nonce", "trace")
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    METRIC_FIELD_NUMBER: _ClassVar[int]
    Z_UM_FIELD_NUMBER: _ClassVar[int]
    SCORES_FIELD_NUMBER: _ClassVar[int]
    BEST_Z_UM_FIELD_NUMBER: _ClassVar[int]
    SIGMA_UM_FIELD_NUMBER: _ClassVar[int]
    FLAGS_FIELD_NUMBER: _ClassVar[int]
    COMPUTE_TIME_S_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    INSTRUMENT_FIELD_NUMBER: _ClassVar[int]
    RUNNER_UP_Z_UM_FIELD_NUMBER: _ClassVar[int]
    CHOSEN_PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    NONCE_FIELD_NUMBER: _ClassVar[int]
    TRACE_FIELD_NUMBER: _ClassVar[int]
    slide: str
    row: int
    col: int
    sequence: int
    metric: str
    z_um: _containers.RepeatedScalarFieldContainer[float]
    scores: _containers.RepeatedScalarFieldContainer[float]
    best_z_um: float
    sigma_um: float
    flags: _containers.RepeatedScalarFieldContainer[_common_pb2.FocusFlag]
    compute_time_s: float
    error: _common_pb2.Error
    instrument: str
    runner_up_z_um: float
    chosen_probability: float
    nonce: bytes
    trace: _common_pb2.TraceContext
    def __init__(self, slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ..., sequence: _Optional[int] = ..., metric: _Optional[str] = ..., z_um: _Optional[_Iterable[float]] = ..., scores: _Optional[_Iterable[float]] = ..., best_z_um: _Optional[float] = ..., sigma_um: _Optional[float] = ..., flags: _Optional[_Iterable[_Union[_common_pb2.FocusFlag, str]]] = ..., compute_time_s: _Optional[float] = ..., error: _Optional[_Union[_common_pb2.Error, _Mapping]] = ..., instrument: _Optional[str] = ..., runner_up_z_um: _Optional[float] = ..., chosen_probability: _Optional[float] = ..., nonce: _Optional[bytes] = ..., trace: _Optional[_Union[_common_pb2.TraceContext, _Mapping]] = ...) -> None: ...
