from focustrack_core.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class AcquisitionPurpose(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ACQUISITION_PURPOSE_FOCUS: _ClassVar[AcquisitionPurpose]
    ACQUISITION_PURPOSE_PHASE: _ClassVar[AcquisitionPurpose]
ACQUISITION_PURPOSE_FOCUS: AcquisitionPurpose
ACQUISITION_PURPOSE_PHASE: AcquisitionPurpose

class AcquireRequest(_message.Message):
    __slots__ = ("slide", "row", "col", "z_low_um", "z_step_um", "n_frames", "sequence", "exposure_s", "nonce", "purpose", "reference_z_um", "stage_offset_x_um", "stage_offset_y_um", "prior_z_um", "prior_sigma_um")
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    Z_LOW_UM_FIELD_NUMBER: _ClassVar[int]
    Z_STEP_UM_FIELD_NUMBER: _ClassVar[int]
    N_FRAMES_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    EXPOSURE_S_FIELD_NUMBER: _ClassVar[int]
    NONCE_FIELD_NUMBER: _ClassVar[int]
    PURPOSE_FIELD_NUMBER: _ClassVar[int]
    REFERENCE_Z_UM_FIELD_NUMBER: _ClassVar[int]
    STAGE_OFFSET_X_UM_FIELD_NUMBER: _ClassVar[int]
    STAGE_OFFSET_Y_UM_FIELD_NUMBER: _ClassVar[int]
    PRIOR_Z_UM_FIELD_NUMBER: _ClassVar[int]
    PRIOR_SIGMA_UM_FIELD_NUMBER: _ClassVar[int]
    slide: str
    row: int
    col: int
    z_low_um: float
    z_step_um: float
    n_frames: int
    sequence: int
    exposure_s: float
    nonce: bytes
    purpose: AcquisitionPurpose
    reference_z_um: float
    stage_offset_x_um: float
    stage_offset_y_um: float
    prior_z_um: float
    prior_sigma_um: float
    def __init__(self, slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ..., z_low_um: _Optional[float] = ..., z_step_um: _Optional[float] = ..., n_frames: _Optional[int] = ..., sequence: _Optional[int] = ..., exposure_s: _Optional[float] = ..., nonce: _Optional[bytes] = ..., purpose: _Optional[_Union[AcquisitionPurpose, str]] = ..., reference_z_um: _Optional[float] = ..., stage_offset_x_um: _Optional[float] = ..., stage_offset_y_um: _Optional[float] = ..., prior_z_um: _Optional[float] = ..., prior_sigma_um: _Optional[float] = ...) -> None: ...

class Timing(_message.Message):
    __slots__ = ("move_s", "z_settle_s", "exposure_s", "readout_s", "total_s", "clock_s", "move_distance_um")
    MOVE_S_FIELD_NUMBER: _ClassVar[int]
    Z_SETTLE_S_FIELD_NUMBER: _ClassVar[int]
    EXPOSURE_S_FIELD_NUMBER: _ClassVar[int]
    READOUT_S_FIELD_NUMBER: _ClassVar[int]
    TOTAL_S_FIELD_NUMBER: _ClassVar[int]
    CLOCK_S_FIELD_NUMBER: _ClassVar[int]
    MOVE_DISTANCE_UM_FIELD_NUMBER: _ClassVar[int]
    move_s: float
    z_settle_s: float
    exposure_s: float
    readout_s: float
    total_s: float
    clock_s: float
    move_distance_um: float
    def __init__(self, move_s: _Optional[float] = ..., z_settle_s: _Optional[float] = ..., exposure_s: _Optional[float] = ..., readout_s: _Optional[float] = ..., total_s: _Optional[float] = ..., clock_s: _Optional[float] = ..., move_distance_um: _Optional[float] = ...) -> None: ...

class ZStackHeader(_message.Message):
    __slots__ = ("instrument", "slide", "row", "col", "sequence", "stage_x_um", "stage_y_um", "z_um", "pixel_size_um", "dtype", "shape", "channel_order", "bit_depth", "exposure_s", "timestamp_unix_s", "clock_s", "nonce", "tag", "purpose", "reference_z_um", "wavelength_um", "condenser_na", "objective_na", "photons_per_count", "dark_counts", "prior_z_um", "prior_sigma_um", "trace")
    INSTRUMENT_FIELD_NUMBER: _ClassVar[int]
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    STAGE_X_UM_FIELD_NUMBER: _ClassVar[int]
    STAGE_Y_UM_FIELD_NUMBER: _ClassVar[int]
    Z_UM_FIELD_NUMBER: _ClassVar[int]
    PIXEL_SIZE_UM_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    CHANNEL_ORDER_FIELD_NUMBER: _ClassVar[int]
    BIT_DEPTH_FIELD_NUMBER: _ClassVar[int]
    EXPOSURE_S_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_UNIX_S_FIELD_NUMBER: _ClassVar[int]
    CLOCK_S_FIELD_NUMBER: _ClassVar[int]
    NONCE_FIELD_NUMBER: _ClassVar[int]
    TAG_FIELD_NUMBER: _ClassVar[int]
    PURPOSE_FIELD_NUMBER: _ClassVar[int]
    REFERENCE_Z_UM_FIELD_NUMBER: _ClassVar[int]
    WAVELENGTH_UM_FIELD_NUMBER: _ClassVar[int]
    CONDENSER_NA_FIELD_NUMBER: _ClassVar[int]
    OBJECTIVE_NA_FIELD_NUMBER: _ClassVar[int]
    PHOTONS_PER_COUNT_FIELD_NUMBER: _ClassVar[int]
    DARK_COUNTS_FIELD_NUMBER: _ClassVar[int]
    PRIOR_Z_UM_FIELD_NUMBER: _ClassVar[int]
    PRIOR_SIGMA_UM_FIELD_NUMBER: _ClassVar[int]
    TRACE_FIELD_NUMBER: _ClassVar[int]
    instrument: str
    slide: str
    row: int
    col: int
    sequence: int
    stage_x_um: float
    stage_y_um: float
    z_um: _containers.RepeatedScalarFieldContainer[float]
    pixel_size_um: float
    dtype: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    channel_order: str
    bit_depth: int
    exposure_s: float
    timestamp_unix_s: float
    clock_s: float
    nonce: bytes
    tag: bytes
    purpose: AcquisitionPurpose
    reference_z_um: float
    wavelength_um: float
    condenser_na: float
    objective_na: float
    photons_per_count: float
    dark_counts: float
    prior_z_um: float
    prior_sigma_um: float
    trace: _common_pb2.TraceContext
    def __init__(self, instrument: _Optional[str] = ..., slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ..., sequence: _Optional[int] = ..., stage_x_um: _Optional[float] = ..., stage_y_um: _Optional[float] = ..., z_um: _Optional[_Iterable[float]] = ..., pixel_size_um: _Optional[float] = ..., dtype: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., channel_order: _Optional[str] = ..., bit_depth: _Optional[int] = ..., exposure_s: _Optional[float] = ..., timestamp_unix_s: _Optional[float] = ..., clock_s: _Optional[float] = ..., nonce: _Optional[bytes] = ..., tag: _Optional[bytes] = ..., purpose: _Optional[_Union[AcquisitionPurpose, str]] = ..., reference_z_um: _Optional[float] = ..., wavelength_um: _Optional[float] = ..., condenser_na: _Optional[float] = ..., objective_na: _Optional[float] = ..., photons_per_count: _Optional[float] = ..., dark_counts: _Optional[float] = ..., prior_z_um: _Optional[float] = ..., prior_sigma_um: _Optional[float] = ..., trace: _Optional[_Union[_common_pb2.TraceContext, _Mapping]] = ...) -> None: ...

class ZFrameHeader(_message.Message):
    __slots__ = ("stack", "index", "timestamp_unix_s", "parts", "part_offset", "tag")
    STACK_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_UNIX_S_FIELD_NUMBER: _ClassVar[int]
    PARTS_FIELD_NUMBER: _ClassVar[int]
    PART_OFFSET_FIELD_NUMBER: _ClassVar[int]
    TAG_FIELD_NUMBER: _ClassVar[int]
    stack: ZStackHeader
    index: int
    timestamp_unix_s: float
    parts: int
    part_offset: int
    tag: bytes
    def __init__(self, stack: _Optional[_Union[ZStackHeader, _Mapping]] = ..., index: _Optional[int] = ..., timestamp_unix_s: _Optional[float] = ..., parts: _Optional[int] = ..., part_offset: _Optional[int] = ..., tag: _Optional[bytes] = ...) -> None: ...

class ZStack(_message.Message):
    __slots__ = ("header", "pixels")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    PIXELS_FIELD_NUMBER: _ClassVar[int]
    header: ZStackHeader
    pixels: bytes
    def __init__(self, header: _Optional[_Union[ZStackHeader, _Mapping]] = ..., pixels: _Optional[bytes] = ...) -> None: ...

class AcquireReply(_message.Message):
    __slots__ = ("header", "timing")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    TIMING_FIELD_NUMBER: _ClassVar[int]
    header: ZStackHeader
    timing: Timing
    def __init__(self, header: _Optional[_Union[ZStackHeader, _Mapping]] = ..., timing: _Optional[_Union[Timing, _Mapping]] = ...) -> None: ...

class FramesRequest(_message.Message):
    __slots__ = ("slide", "row", "col", "sequence", "indices")
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    INDICES_FIELD_NUMBER: _ClassVar[int]
    slide: str
    row: int
    col: int
    sequence: int
    indices: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ..., sequence: _Optional[int] = ..., indices: _Optional[_Iterable[int]] = ...) -> None: ...

class SlideInfo(_message.Message):
    __slots__ = ("slide", "rows", "cols", "pitch_um", "origin_x_um", "origin_y_um")
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROWS_FIELD_NUMBER: _ClassVar[int]
    COLS_FIELD_NUMBER: _ClassVar[int]
    PITCH_UM_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_X_UM_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_Y_UM_FIELD_NUMBER: _ClassVar[int]
    slide: str
    rows: int
    cols: int
    pitch_um: float
    origin_x_um: float
    origin_y_um: float
    def __init__(self, slide: _Optional[str] = ..., rows: _Optional[int] = ..., cols: _Optional[int] = ..., pitch_um: _Optional[float] = ..., origin_x_um: _Optional[float] = ..., origin_y_um: _Optional[float] = ...) -> None: ...

class InstrumentInfo(_message.Message):
    __slots__ = ("instrument", "slides", "z_min_um", "z_max_um", "max_frames", "pixel_size_um", "width", "height", "channel_order", "bit_depth", "numerical_aperture", "magnification", "wavelength_um", "refractive_index", "depth_of_field_um", "default_exposure_s", "hardware_sequenced", "laser")
    INSTRUMENT_FIELD_NUMBER: _ClassVar[int]
    SLIDES_FIELD_NUMBER: _ClassVar[int]
    Z_MIN_UM_FIELD_NUMBER: _ClassVar[int]
    Z_MAX_UM_FIELD_NUMBER: _ClassVar[int]
    MAX_FRAMES_FIELD_NUMBER: _ClassVar[int]
    PIXEL_SIZE_UM_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    CHANNEL_ORDER_FIELD_NUMBER: _ClassVar[int]
    BIT_DEPTH_FIELD_NUMBER: _ClassVar[int]
    NUMERICAL_APERTURE_FIELD_NUMBER: _ClassVar[int]
    MAGNIFICATION_FIELD_NUMBER: _ClassVar[int]
    WAVELENGTH_UM_FIELD_NUMBER: _ClassVar[int]
    REFRACTIVE_INDEX_FIELD_NUMBER: _ClassVar[int]
    DEPTH_OF_FIELD_UM_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_EXPOSURE_S_FIELD_NUMBER: _ClassVar[int]
    HARDWARE_SEQUENCED_FIELD_NUMBER: _ClassVar[int]
    LASER_FIELD_NUMBER: _ClassVar[int]
    instrument: str
    slides: _containers.RepeatedCompositeFieldContainer[SlideInfo]
    z_min_um: float
    z_max_um: float
    max_frames: int
    pixel_size_um: float
    width: int
    height: int
    channel_order: str
    bit_depth: int
    numerical_aperture: float
    magnification: float
    wavelength_um: float
    refractive_index: float
    depth_of_field_um: float
    default_exposure_s: float
    hardware_sequenced: bool
    laser: bool
    def __init__(self, instrument: _Optional[str] = ..., slides: _Optional[_Iterable[_Union[SlideInfo, _Mapping]]] = ..., z_min_um: _Optional[float] = ..., z_max_um: _Optional[float] = ..., max_frames: _Optional[int] = ..., pixel_size_um: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., channel_order: _Optional[str] = ..., bit_depth: _Optional[int] = ..., numerical_aperture: _Optional[float] = ..., magnification: _Optional[float] = ..., wavelength_um: _Optional[float] = ..., refractive_index: _Optional[float] = ..., depth_of_field_um: _Optional[float] = ..., default_exposure_s: _Optional[float] = ..., hardware_sequenced: _Optional[bool] = ..., laser: _Optional[bool] = ...) -> None: ...

class SlideTruth(_message.Message):
    __slots__ = ("instrument", "slide", "rows", "cols", "best_focus_um", "drift_um", "clock_s", "tissue_share", "empty", "dust_z_um", "fold_z_um", "lateral_offset_x_um", "lateral_offset_y_um")
    INSTRUMENT_FIELD_NUMBER: _ClassVar[int]
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROWS_FIELD_NUMBER: _ClassVar[int]
    COLS_FIELD_NUMBER: _ClassVar[int]
    BEST_FOCUS_UM_FIELD_NUMBER: _ClassVar[int]
    DRIFT_UM_FIELD_NUMBER: _ClassVar[int]
    CLOCK_S_FIELD_NUMBER: _ClassVar[int]
    TISSUE_SHARE_FIELD_NUMBER: _ClassVar[int]
    EMPTY_FIELD_NUMBER: _ClassVar[int]
    DUST_Z_UM_FIELD_NUMBER: _ClassVar[int]
    FOLD_Z_UM_FIELD_NUMBER: _ClassVar[int]
    LATERAL_OFFSET_X_UM_FIELD_NUMBER: _ClassVar[int]
    LATERAL_OFFSET_Y_UM_FIELD_NUMBER: _ClassVar[int]
    instrument: str
    slide: str
    rows: int
    cols: int
    best_focus_um: _containers.RepeatedScalarFieldContainer[float]
    drift_um: float
    clock_s: float
    tissue_share: _containers.RepeatedScalarFieldContainer[float]
    empty: _containers.RepeatedScalarFieldContainer[bool]
    dust_z_um: _containers.RepeatedScalarFieldContainer[float]
    fold_z_um: _containers.RepeatedScalarFieldContainer[float]
    lateral_offset_x_um: float
    lateral_offset_y_um: float
    def __init__(self, instrument: _Optional[str] = ..., slide: _Optional[str] = ..., rows: _Optional[int] = ..., cols: _Optional[int] = ..., best_focus_um: _Optional[_Iterable[float]] = ..., drift_um: _Optional[float] = ..., clock_s: _Optional[float] = ..., tissue_share: _Optional[_Iterable[float]] = ..., empty: _Optional[_Iterable[bool]] = ..., dust_z_um: _Optional[_Iterable[float]] = ..., fold_z_um: _Optional[_Iterable[float]] = ..., lateral_offset_x_um: _Optional[float] = ..., lateral_offset_y_um: _Optional[float] = ...) -> None: ...

class PhaseTruth(_message.Message):
    __slots__ = ("instrument", "slide", "row", "col", "shape", "dtype", "pixel_size_um", "focus_z_um")
    INSTRUMENT_FIELD_NUMBER: _ClassVar[int]
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    PIXEL_SIZE_UM_FIELD_NUMBER: _ClassVar[int]
    FOCUS_Z_UM_FIELD_NUMBER: _ClassVar[int]
    instrument: str
    slide: str
    row: int
    col: int
    shape: _containers.RepeatedScalarFieldContainer[int]
    dtype: str
    pixel_size_um: float
    focus_z_um: float
    def __init__(self, instrument: _Optional[str] = ..., slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ..., shape: _Optional[_Iterable[int]] = ..., dtype: _Optional[str] = ..., pixel_size_um: _Optional[float] = ..., focus_z_um: _Optional[float] = ...) -> None: ...

class LaserRequest(_message.Message):
    __slots__ = ("slide", "row", "col")
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    slide: str
    row: int
    col: int
    def __init__(self, slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ...) -> None: ...

class LaserReading(_message.Message):
    __slots__ = ("instrument", "slide", "row", "col", "z_um", "sigma_um", "timing")
    INSTRUMENT_FIELD_NUMBER: _ClassVar[int]
    SLIDE_FIELD_NUMBER: _ClassVar[int]
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    Z_UM_FIELD_NUMBER: _ClassVar[int]
    SIGMA_UM_FIELD_NUMBER: _ClassVar[int]
    TIMING_FIELD_NUMBER: _ClassVar[int]
    instrument: str
    slide: str
    row: int
    col: int
    z_um: float
    sigma_um: float
    timing: Timing
    def __init__(self, instrument: _Optional[str] = ..., slide: _Optional[str] = ..., row: _Optional[int] = ..., col: _Optional[int] = ..., z_um: _Optional[float] = ..., sigma_um: _Optional[float] = ..., timing: _Optional[_Union[Timing, _Mapping]] = ...) -> None: ...
