"""The instruments `focustrack serve instrument --backend NAME` serves, and their options.

Each backend adds its options to the command (all of them show in `--help`) and opens
its instrument from the parsed options. A backend's code, and what it needs (the
simulator: scipy and OpenCV; a real microscope: its drivers), is imported only when
the service opens it: `--help` and a bad option cost none of it.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

from focustrack_instrument_sim.instrument import Instrument


@dataclass(frozen=True)
class Backend:
    """A kind of instrument: `help` for `--backend`, its options, and how it opens."""

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    open: Callable[[argparse.Namespace], Instrument]  # ValueError: a bad option


def add_simulator_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulator's slides and microscope."""
    from focustrack_core.surfaces import FAMILIES  # numpy only

    slides = parser.add_argument_group("slides (--backend sim)")
    slides.add_argument("--seed", type=int, default=0, help="seed of surfaces and specimens")
    slides.add_argument("--slides", type=int, default=1, help="generated slides (slide-0, ...)")
    slides.add_argument("--rows", type=int, default=20, help="tiles per column of a slide")
    slides.add_argument("--cols", type=int, default=20, help="tiles per row of a slide")
    slides.add_argument("--family", choices=list(FAMILIES), default="standard")
    slides.add_argument("--map", help="true focus map(s) in um (.npy, .csv, .tif) to use instead")
    slides.add_argument("--pitch-um", type=float, default=200.0, help="tile centre spacing")
    slides.add_argument(
        "--z-offset-um",
        type=float,
        default=0.0,
        help="every slide's focus moved by this much (a re-scan after drift between passes)",
    )
    scope = parser.add_argument_group("microscope (--backend sim)")
    scope.add_argument("--width", type=int, default=1024, help="frame width in pixels")
    scope.add_argument("--height", type=int, default=1024, help="frame height in pixels")
    scope.add_argument("--max-frames", type=int, default=64, help="largest z-stack accepted")
    scope.add_argument(
        "--workers", type=int, default=2, help="threads rendering the frames of a stack (2)"
    )
    scope.add_argument(
        "--cache-mb",
        type=float,
        default=1024.0,
        help="in-focus tile spectra kept, MB (1024: 244 tiles of 512 x 512, 61 of 1024 x 1024)",
    )
    scope.add_argument("--na", type=float, default=0.85, help="numerical aperture")
    scope.add_argument("--magnification", type=float, default=60.0)
    scope.add_argument("--drift-um-per-s", type=float, default=0.0, help="thermal z drift")
    scope.add_argument("--dust-density", type=float, default=0.0, help="specks per 1000 um^2")


def open_simulator(args: argparse.Namespace) -> Instrument:
    from focustrack_instrument_sim.simulated import SimulatedInstrument, microscope_from_args

    return SimulatedInstrument(microscope_from_args(args))


#: --backend NAME -> the backend.
BACKENDS: dict[str, Backend] = {
    "sim": Backend("the simulated microscope", add_simulator_arguments, open_simulator),
}
