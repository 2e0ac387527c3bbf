"""The settings of a scan, in one model: flags, ``FOCUSTRACK_SCAN_<OPTION>`` and a settings file.

`ScanOptions` are the options a scan shares with `focustrack demo` (the prior, the
z-stacks, the phase stacks, timeouts and retries, the mosaic's format, the progress bar,
the result key);
`ScanSettings`, the `focustrack scan` command's, adds what to scan, where the estimator
and the bus are, and where the outputs go. Each default is written once: the prior's and
the z-stacks' are the estimator API's (`focustrack_client.models`), the timeouts are
`retry.RetryPolicy`'s, and the others are here; `ScanOptions.request` and `retry` hand them
to the scan's own objects.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar, Self
from urllib.parse import urlsplit

from pydantic import BaseModel, Field, field_validator, model_validator
from pydantic_settings import CliToggleFlag, NoDecode, SettingsConfigDict

from focustrack_client import models as api
from focustrack_core.http_metrics import MetricsPortSettings
from focustrack_core.rest.to_domain import default_policy
from focustrack_core.settings import ServiceSettings
from focustrack_core.tracing import TracingSettings
from focustrack_core.wire.session import CONNECT_TIMEOUT_S, DEFAULT_ENDPOINT, ZenohSettings
from focustrack_scheduler.outputs import MosaicFormat
from focustrack_scheduler.plan import PhaseStacks, ScanRequest
from focustrack_scheduler.realign import Realign, first_pass_mosaic
from focustrack_scheduler.retry import RetryPolicy

#: The best Kalman strategy we have, the demo's headline. kf-2d has the lowest prior MAE at
#: the simulator's focus noise (0.146 um against 0.284 for kf-wiener0 and 0.254 for kf-mmae,
#: 8 standard 10x10 maps, `focustrack bench accuracy --noise-um 0.1 --dof-um 0.89`) and at
#: the thesis' 1.5 um noise (0.461 against 0.612 for kf-mmae, 16 maps of 20x20).
BEST_KALMAN = "kf-2d"

#: The estimator's bearer token when no option gives one (the estimator's own variable).
TOKEN_ENV = "FOCUSTRACK_ESTIMATOR_TOKEN"

_RETRY = RetryPolicy()
_REALIGN = Realign(Path())


def _api_field(model: type[BaseModel], name: str, description: str) -> Any:
    """An option with the default and bounds of the estimator API's field `model.name`."""
    api_field = model.model_fields[name]
    option = Field(api_field.default, description=description)
    option.metadata = list(api_field.metadata)  # the bounds (annotated-types' Ge, Le, ...)
    return option


def _estimator_token() -> str | None:
    return os.environ.get(TOKEN_ENV) or None


#: The options of the phase stacks, which only `--phase` takes.
_PHASE_OPTIONS = ("phase_planes", "phase_step_um", "phase_timeout_s", "phase_in_flight")


class ScanOptions(ServiceSettings):
    """How a scan is made, shared by `focustrack scan` and `focustrack demo`."""

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_SCAN_")

    # what is known before the first tile
    start_z_um: float = _api_field(api.SlideCreate, "start_z_um", "start height, um")
    start_sigma_um: float = _api_field(api.SlideCreate, "start_sigma_um", "its std, um")
    noise_sigma_um: api.Sigma = Field(
        0.1, description="std of a best-focus measurement without its own sigma, um"
    )
    # z-stacks
    k_sigma: float = _api_field(
        api.ZRangePolicy, "k_sigma", "a stack spans +/- this many predicted sigmas"
    )
    z_step_um: float = _api_field(api.ZRangePolicy, "z_step_um", "between frames, um")
    min_frames: int = _api_field(api.ZRangePolicy, "min_frames", "frames of a stack, at least")
    max_frames: int = _api_field(api.ZRangePolicy, "max_frames", "frames of a stack, at most")
    # timeouts and retries
    instrument_timeout_s: float = Field(
        _RETRY.instrument_timeout_s, gt=0, description="one instrument query, s"
    )
    instrument_outage_s: float = Field(
        _RETRY.instrument_outage_s,
        gt=0,
        description="how long to keep retrying an instrument (or router) that does not answer "
        "or is busy, with pauses doubling up to 5 s",
    )
    focus_timeout_s: float = Field(
        _RETRY.focus_timeout_s, gt=0, description="the wait for a stack's focus result, s"
    )
    focus_attempts: int = Field(
        5,
        ge=1,
        description="acquisitions of a stack without result (with --focus-timeout-s, rides "
        "out a focus service restart of a minute)",
    )
    estimator_outage_s: float = Field(
        _RETRY.estimator_outage_s,
        gt=0,
        description="how long to keep retrying an estimator that does not answer",
    )
    # phase
    phase: bool = Field(
        False,
        description="also take a phase stack of every tile, centred on the z its image is "
        "taken at, for the phase service (`focustrack serve phase`), and keep its phase in "
        "radians beside the mosaic (docs/phase.md)",
    )
    phase_planes: int = Field(
        11,
        ge=2,
        description="frames of a phase stack: 11 at the default step span +/- 2.5 depths of "
        "field, where the phase contrast of everything the objective resolves has grown "
        "(the prediction puts the tile's focus in the middle, so a short stack is enough)",
    )
    phase_step_um: float | None = Field(
        None,
        gt=0,
        description="between the frames of a phase stack, um (default: half the objective's "
        "depth of field, from the instrument's info: 0.45 um at the simulator's 60x/0.85)",
    )
    phase_timeout_s: float = Field(
        _RETRY.phase_timeout_s,
        gt=0,
        description="the wait for a phase stack's result, s; none by then: the tile has no phase",
    )
    phase_in_flight: int = Field(
        _RETRY.phase_in_flight,
        ge=0,
        description="phase stacks whose results the scan goes on without: it images the next "
        "tile while the phase service reconstructs the last (0: it waits for each result; "
        "the scan waits for every result still to come before it ends)",
    )
    # outputs and trust
    mosaic_format: MosaicFormat = Field(
        MosaicFormat.OME_ZARR,
        description="file of the mosaic: mosaic.ome.zarr (ome-zarr) or mosaic.ome.tif",
    )
    no_progress: CliToggleFlag[bool] = Field(False, description="hide the progress bar")
    result_key_file: Path | None = Field(
        None,
        description="the focus (and phase) service's shared key: accept only results tagged "
        "with it (docs/security.md; default: any result with the awaited acquisition's nonce)",
    )

    @model_validator(mode="after")
    def _frames_in_order(self) -> Self:
        # Said here, in the options' words: the z-stack policy's own check is a pydantic
        # dump of the estimator API's model.
        if self.min_frames > self.max_frames:
            raise ValueError(
                f"--min-frames {self.min_frames} is above --max-frames {self.max_frames}"
            )
        return self

    @classmethod
    def defaults(cls, **changes: Any) -> ScanOptions:
        """The options' defaults with `changes` over them, checked, without reading the
        environment (for scans that code makes: benchmarks, tests)."""
        return cls.load(environment=False, **changes)

    def request(
        self, instrument: str, slide: str, strategy: str, params: Mapping[str, Any] | None = None
    ) -> ScanRequest:
        """The scan of `slide` on `instrument` with `strategy` (and its `params`), as these
        options make it (ValueError on a bad name or z-stack policy)."""
        return ScanRequest(
            instrument=instrument,
            slide=slide,
            strategy=strategy,
            params=dict(params or {}),
            start_z_um=self.start_z_um,
            start_sigma_um=self.start_sigma_um,
            noise_sigma_um=self.noise_sigma_um,
            policy=default_policy(
                k_sigma=self.k_sigma,
                z_step_um=self.z_step_um,
                min_frames=self.min_frames,
                max_frames=self.max_frames,
            ),
            focus_attempts=self.focus_attempts,
            phase=PhaseStacks(self.phase_planes, self.phase_step_um) if self.phase else None,
        )

    def ignored_phase_options(self) -> list[str]:
        """The phase stacks' options given (flags, environment or settings file) without
        `--phase`, which they change nothing without."""
        if self.phase:
            return []
        given = self.model_fields_set
        return [f"--{name.replace('_', '-')}" for name in _PHASE_OPTIONS if name in given]

    def retry(self) -> RetryPolicy:
        """The timeouts and retries these options set (the others as `RetryPolicy` has them)."""
        return RetryPolicy(
            instrument_timeout_s=self.instrument_timeout_s,
            instrument_outage_s=self.instrument_outage_s,
            focus_timeout_s=self.focus_timeout_s,
            phase_timeout_s=self.phase_timeout_s,
            phase_in_flight=self.phase_in_flight,
            estimator_outage_s=self.estimator_outage_s,
        )


class ScanSettings(ZenohSettings, ScanOptions, MetricsPortSettings, TracingSettings):
    """The settings of `focustrack scan` (and `focustrack-scheduler`)."""

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_SCAN_")
    default_connect: ClassVar[tuple[str, ...]] = (DEFAULT_ENDPOINT,)

    bus_timeout_s: float = Field(
        CONNECT_TIMEOUT_S,
        gt=0,
        le=86400,
        description="how long the scan waits for a Zenoh router (or peer) at --connect before "
        "it gives up (exit 1), s",
    )
    estimator: str = Field("http://127.0.0.1:8100", description="estimator URL")
    token: str | None = Field(
        default_factory=_estimator_token,
        description=f"estimator bearer token (default ${TOKEN_ENV})",
    )
    instrument: str = Field("sim", description="instrument name")
    slide: str = Field("slide-0", description="slide name")
    strategy: str = Field(BEST_KALMAN, description="strategy")
    param: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="a strategy parameter, NAME=VALUE, the value read as JSON where it parses "
        "(repeat the option)",
    )
    out: Path = Field(Path("out/scan"), description="output folder")
    first_pass: Path | None = Field(
        None,
        description="a second pass: the first pass's output folder (its mosaic.ome.zarr); this "
        "pass's lateral offset is measured against its images and the stage moved by it, so "
        "that the tiles land where the first pass's were (docs/drift.md)",
    )
    lateral_tiles: int = Field(
        _REALIGN.tiles,
        ge=1,
        description="with --first-pass: tiles whose images must agree on the offset",
    )
    lateral_max_um: float = Field(
        _REALIGN.max_offset_um, gt=0, description="with --first-pass: the largest offset, um"
    )
    frame_check_ratio: float = Field(
        _REALIGN.min_sharpness_ratio,
        ge=0,
        lt=1,
        description="with --first-pass: a tile imaged with one frame at its prediction is "
        "measured where that frame's sharpness is below this share of the first pass's image "
        "of the tile (0: no check; docs/drift.md)",
    )
    live_port: int | None = Field(
        None,
        ge=0,
        le=65535,
        description="serve the live web view of the scan on this port of --live-host "
        "(0: any free one)",
    )
    live_host: str = Field(
        "127.0.0.1",
        min_length=1,
        description="the address the live web view listens on (0.0.0.0: every interface, "
        "as in a container whose port is published)",
    )

    @field_validator("estimator")
    @classmethod
    def _http_url(cls, url: str) -> str:
        """An http(s) URL with a host: anything else would be retried as an outage."""
        parsed = urlsplit(url)
        if parsed.scheme not in ("http", "https") or not parsed.hostname:
            raise ValueError(f"must be an http:// or https:// URL with a host, got {url!r}")
        return url

    @field_validator("first_pass")
    @classmethod
    def _a_finished_scan(cls, folder: Path | None) -> Path | None:
        """A folder holding a mosaic, said before the bus (it was said once the first tile's
        grid was known, exit 1, a scan record left in --out)."""
        if folder is not None:
            first_pass_mosaic(folder)
        return folder

    @field_validator("param", mode="before")
    @classmethod
    def _param_items(cls, value: Any) -> Any:
        """One item (the environment's NAME=VALUE) or a JSON list of them (the flags')."""
        if isinstance(value, str):
            return json.loads(value) if value.startswith("[") else [value]
        return value

    @field_validator("param")
    @classmethod
    def _named(cls, items: list[str]) -> list[str]:
        for item in items:
            name, equals, _ = item.partition("=")
            if not (name and equals):
                raise ValueError(f"takes NAME=VALUE, got {item!r}")
        return items

    @classmethod
    def from_args(cls, args: argparse.Namespace, *, environment: bool = True) -> Self:
        # The --param items reach the model as one JSON list: a list option's items are
        # otherwise split at commas, and a parameter's value may hold some ("[1.0, 2.0]").
        flags = vars(args).copy()
        if flags.get("param") is not None:
            flags["param"] = json.dumps(flags["param"])
        return super().from_args(argparse.Namespace(**flags), environment=environment)

    @property
    def params(self) -> dict[str, Any]:
        """The strategy parameters by name; values read as JSON where they parse."""
        params: dict[str, Any] = {}
        for item in self.param:
            name, _, text = item.partition("=")
            try:
                params[name] = json.loads(text)
            except json.JSONDecodeError:
                params[name] = text
        return params

    def scan_request(self) -> ScanRequest:
        """The scan these settings describe (ValueError on a bad name or z-stack policy)."""
        request = self.request(self.instrument, self.slide, self.strategy, self.params)
        if self.first_pass is None:
            return request
        realign = Realign(
            self.first_pass, self.lateral_tiles, self.lateral_max_um, self.frame_check_ratio
        )
        return dataclasses.replace(request, realign=realign)
