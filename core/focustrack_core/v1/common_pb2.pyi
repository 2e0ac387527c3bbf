from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ErrorCode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ERROR_CODE_UNSPECIFIED: _ClassVar[ErrorCode]
    ERROR_CODE_MALFORMED_REQUEST: _ClassVar[ErrorCode]
    ERROR_CODE_UNKNOWN_SLIDE: _ClassVar[ErrorCode]
    ERROR_CODE_TILE_OUTSIDE_SLIDE: _ClassVar[ErrorCode]
    ERROR_CODE_Z_OUT_OF_RANGE: _ClassVar[ErrorCode]
    ERROR_CODE_TOO_MANY_FRAMES: _ClassVar[ErrorCode]
    ERROR_CODE_INTERNAL: _ClassVar[ErrorCode]
    ERROR_CODE_BAD_STACK: _ClassVar[ErrorCode]
    ERROR_CODE_TIMEOUT: _ClassVar[ErrorCode]
    ERROR_CODE_UNAVAILABLE: _ClassVar[ErrorCode]
    ERROR_CODE_BUSY: _ClassVar[ErrorCode]
    ERROR_CODE_FRAMES_GONE: _ClassVar[ErrorCode]
    ERROR_CODE_DEVICE_FAILURE: _ClassVar[ErrorCode]
    ERROR_CODE_DEVICE_TIMEOUT: _ClassVar[ErrorCode]
    ERROR_CODE_TARGET_NOT_REACHED: _ClassVar[ErrorCode]
    ERROR_CODE_NO_IMAGE: _ClassVar[ErrorCode]

class FocusFlag(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FOCUS_FLAG_UNSPECIFIED: _ClassVar[FocusFlag]
    FOCUS_FLAG_EDGE_LOW: _ClassVar[FocusFlag]
    FOCUS_FLAG_EDGE_HIGH: _ClassVar[FocusFlag]
    FOCUS_FLAG_FLAT: _ClassVar[FocusFlag]
    FOCUS_FLAG_EMPTY: _ClassVar[FocusFlag]
    FOCUS_FLAG_MULTI_PEAK: _ClassVar[FocusFlag]
    FOCUS_FLAG_AMBIGUOUS: _ClassVar[FocusFlag]
    FOCUS_FLAG_VALLEY: _ClassVar[FocusFlag]
ERROR_CODE_UNSPECIFIED: ErrorCode
ERROR_CODE_MALFORMED_REQUEST: ErrorCode
ERROR_CODE_UNKNOWN_SLIDE: ErrorCode
ERROR_CODE_TILE_OUTSIDE_SLIDE: ErrorCode
ERROR_CODE_Z_OUT_OF_RANGE: ErrorCode
ERROR_CODE_TOO_MANY_FRAMES: ErrorCode
ERROR_CODE_INTERNAL: ErrorCode
ERROR_CODE_BAD_STACK: ErrorCode
ERROR_CODE_TIMEOUT: ErrorCode
ERROR_CODE_UNAVAILABLE: ErrorCode
ERROR_CODE_BUSY: ErrorCode
ERROR_CODE_FRAMES_GONE: ErrorCode
ERROR_CODE_DEVICE_FAILURE: ErrorCode
ERROR_CODE_DEVICE_TIMEOUT: ErrorCode
ERROR_CODE_TARGET_NOT_REACHED: ErrorCode
ERROR_CODE_NO_IMAGE: ErrorCode
FOCUS_FLAG_UNSPECIFIED: FocusFlag
FOCUS_FLAG_EDGE_LOW: FocusFlag
FOCUS_FLAG_EDGE_HIGH: FocusFlag
FOCUS_FLAG_FLAT: FocusFlag
FOCUS_FLAG_EMPTY: FocusFlag
FOCUS_FLAG_MULTI_PEAK: FocusFlag
FOCUS_FLAG_AMBIGUOUS: FocusFlag
FOCUS_FLAG_VALLEY: FocusFlag

class Error(_message.Message):
    __slots__ = ("code", "message", "field")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    FIELD_FIELD_NUMBER: _ClassVar[int]
    code: ErrorCode
    message: str
    field: str
    def __init__(self, code: _Optional[_Union[ErrorCode, str]] = ..., message: _Optional[str] = ..., field: _Optional[str] = ...) -> None: ...

class TraceContext(_message.Message):
    __slots__ = ("traceparent", "tracestate")
    TRACEPARENT_FIELD_NUMBER: _ClassVar[int]
    TRACESTATE_FIELD_NUMBER: _ClassVar[int]
    traceparent: str
    tracestate: str
    def __init__(self, traceparent: _Optional[str] = ..., tracestate: _Optional[str] = ...) -> None: ...
