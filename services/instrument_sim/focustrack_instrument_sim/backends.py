"""The instruments `focustrack serve instrument --backend NAME` serves.

Each backend declares its options as a small pydantic model of its own (the simulator's:
`simulator_options.SimulatorOptions`), which the service's one settings model composes
(`service.InstrumentSettings`: the flags stay flat and all show in `--help`), and opens
its instrument from those settings. A backend's code, and what it needs (the simulator:
scipy and OpenCV; a real microscope: its drivers), is imported only when the service
opens it: `--help` and a bad option cost none of it. A new backend adds its options
model to `service.InstrumentSettings` and its entry to `BACKENDS`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Generic, TypeVar

from pydantic import BaseModel

from focustrack_core.settings import one_of
from focustrack_instrument_sim.instrument import Instrument
from focustrack_instrument_sim.mmcore_options import MMCoreOptions
from focustrack_instrument_sim.simulator_options import SimulatorOptions

Options = TypeVar("Options", bound=BaseModel)


@dataclass(frozen=True)
class Backend(Generic[Options]):
    """A kind of instrument: `help` for `--backend`, and how it opens from its options
    (the service's settings, which include them)."""

    help: str
    open: Callable[[Options], Instrument]  # ValueError: a bad option


def open_simulator(options: SimulatorOptions) -> Instrument:
    from focustrack_instrument_sim.simulated import simulated_instrument

    return simulated_instrument(options)


def open_mmcore(options: MMCoreOptions) -> Instrument:
    from focustrack_instrument_sim.mmcore_backend import (
        MMCoreInstrument,
        core_from_config,
        release_core,
    )

    if options.mm_config is None:
        raise ValueError("--backend mmcore needs --mm-config FILE (a Micro-Manager configuration)")
    # pymmcore-plus logs to stderr (WARNING and up, PYMM_LOG_LEVEL) and to a file of its own;
    # passed on to the service's log as well, every line would show twice, DEBUG included.
    logging.getLogger("pymmcore-plus").propagate = False
    core = core_from_config(options.mm_config, options.mm_adapter_path)
    try:
        return MMCoreInstrument(core, options)
    except BaseException:
        release_core(core)
        raise


def open_mmcore_sim(options: SimulatorOptions) -> Instrument:
    """The simulator's microscope behind the MMCore backend; `options` (the service's
    settings) hold the MMCore backend's options too."""
    from focustrack_instrument_sim.mmcore_sim import SimulatedMMCoreInstrument
    from focustrack_instrument_sim.simulated import microscope_from_options

    logging.getLogger("pymmcore-plus").propagate = False  # as open_mmcore's
    mmcore_options = MMCoreOptions.model_validate(options, from_attributes=True)
    microscope = microscope_from_options(options)
    try:
        return SimulatedMMCoreInstrument(microscope, mmcore_options)
    except BaseException:
        microscope.close()
        raise


#: --backend NAME -> the backend.
BACKENDS: dict[str, Backend[Any]] = {
    "sim": Backend("the simulated microscope", open_simulator),
    "mmcore": Backend("a microscope through Micro-Manager (pymmcore-plus)", open_mmcore),
    "mmcore-sim": Backend(
        "the simulated microscope behind Micro-Manager's device layer (pymmcore-plus "
        "UniMMCore Python devices, served by the mmcore backend)",
        open_mmcore_sim,
    ),
}

#: A backend's name (--backend): one of `BACKENDS`.
BackendName = Annotated[str, one_of(BACKENDS)]
