"""The instrument service's settings: the shell's options and every backend's, flat.

Flags, ``FOCUSTRACK_INSTRUMENT_<OPTION>`` or a settings file (`focustrack_core.settings`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, ClassVar

from pydantic import AfterValidator, Field
from pydantic_settings import SettingsConfigDict

from focustrack_core.http_metrics import MetricsPortSettings
from focustrack_core.tracing import TracingSettings
from focustrack_core.wire import codec, keys
from focustrack_core.wire.session import DEFAULT_ENDPOINT, ZenohSettings
from focustrack_instrument_sim.backends import BACKENDS, BackendName
from focustrack_instrument_sim.mmcore_options import MMCoreOptions
from focustrack_instrument_sim.simulator_options import SimulatorOptions

#: Acquisitions that may wait for the stage; one more is refused BUSY.
QUEUE_DEPTH = 4

#: Frames of past stacks kept for queries, MB, besides the last stack (`RecentStacks`):
#: two stacks of 41 frames of 1024 x 1024 RGB uint16.
KEEP_FRAMES_MB = 512


class InstrumentShellSettings(ZenohSettings, MetricsPortSettings, TracingSettings):
    """The shell's options, whatever the instrument: its name, queue, frames and truth, its
    metrics and traces."""

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_INSTRUMENT_")
    default_listen: ClassVar[tuple[str, ...]] = (DEFAULT_ENDPOINT,)

    name: Annotated[str, AfterValidator(keys.check_name)] = Field(
        "sim", description="instrument name in the key space"
    )
    backend: BackendName = Field(
        "sim",
        description="the instrument served: "
        + ", ".join(f"{name} ({backend.help})" for name, backend in BACKENDS.items()),
    )
    realtime: bool = Field(False, description="pace acquisitions at their simulated duration")
    keep_frames_mb: float = Field(
        KEEP_FRAMES_MB,
        ge=0,
        description="frames of past stacks kept for the frames queryable, MB, besides the "
        "last stack",
    )
    frame_part_kb: int = Field(
        codec.FRAME_PART_BYTES // 1024,
        ge=0,
        description="frames go over the network in parts of this many KiB, 0: whole (the "
        "default is the fastest over TCP; see proto/README.md)",
    )
    queue_depth: int = Field(
        QUEUE_DEPTH,
        ge=1,
        description="acquisitions that may wait for the stage; more are refused BUSY",
    )
    serve_truth: bool = Field(
        False,
        description="answer the ground truth (focustrack/v1/eval/truth/..., and the true "
        "phase: focustrack/v1/eval/phase/...): benchmarks and tests only",
    )
    frame_key_file: Path | None = Field(
        None,
        description="shared key: tag every frame and stack with its HMAC, for the focus "
        "service to check (docs/security.md)",
    )


class InstrumentSettings(MMCoreOptions, SimulatorOptions, InstrumentShellSettings):
    """The service's settings: flags, ``FOCUSTRACK_INSTRUMENT_<OPTION>`` or a settings file.

    The shell's options and every backend's (`backends.BACKENDS`), flat: a backend opens
    from these settings, which are its options too. A new backend adds its options model
    to the bases (and a list option of it to `list_fields`, after the shell's).
    """

    list_fields: ClassVar[tuple[str, ...]] = (
        *InstrumentShellSettings.list_fields,
        "mm_adapter_path",
    )
