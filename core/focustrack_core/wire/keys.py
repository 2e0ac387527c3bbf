"""The Zenoh key space of focustrack (documented for other languages in proto/README.md).

- ``focustrack/v1/instrument/{instrument}/acquire``: queryable; AcquireRequest in,
  AcquireReply out (error replies carry an Error).
- ``focustrack/v1/instrument/{instrument}/info``: queryable; InstrumentInfo out.
- ``focustrack/v1/instrument/{instrument}/frames``: queryable; FramesRequest in, one
  reply per frame of a stack acquired lately (as published on zframe), or an Error.
- ``focustrack/v1/zstack/{slide}/{row}/{col}``: the instrument publishes each whole stack
  (raw pixels as payload, ZStackHeader as attachment) when someone subscribes to it.
- ``focustrack/v1/zframe/{slide}/{row}/{col}``: the instrument publishes every frame of
  a stack as soon as it is acquired (raw pixels of the frame, ZFrameHeader as attachment).
- ``focustrack/v1/focus/{slide}/{row}/{col}``: the focus service publishes a FocusResult.
- ``focustrack/v1/phase/{slide}/{row}/{col}``: the phase service publishes the amplitude and
  phase of each phase stack (float32 (2, height, width) payload, PhaseResult attachment).
- ``focustrack/v1/eval/truth/{instrument}/{slide}``: queryable; SlideTruth out. Ground
  truth for evaluation code only, under its own prefix so that no scanner reads it by
  accident (a scanner subscribes to nothing under ``focustrack/v1/eval``).
- ``focustrack/v1/eval/phase/{instrument}/{slide}/{row}/{col}``: queryable; the true phase
  of a tile (float32 payload, PhaseTruth attachment), for evaluation code only.
- ``focustrack/v1/bench/{name}``: the instrument benchmark's own traffic.
- ``focustrack/v1/alive/{service}/{slides}/{zid}``: a liveliness token each focus
  (``{service}`` ``focus``) and phase service (``phase``) declares once it reads frames
  (``{slides}`` the slides it reads, ``*`` for every slide; ``{zid}`` its session's id).
  A scheduler watches the tokens of its slide (``focustrack/v1/alive/focus/{slide}/*``,
  and ``.../alive/phase/{slide}/*`` with phase stacks): a token that goes takes with it
  the results that service had yet to publish.

Names (instrument, slide) are single key chunks: letters, digits, ``_``, ``-``, ``.``.
"""

from __future__ import annotations

import re
from typing import Literal, NamedTuple

PREFIX = "focustrack/v1"

#: The services that declare a liveliness token while they read frames (`alive_key`).
AliveService = Literal["focus", "phase"]

_NAME = re.compile(r"[A-Za-z0-9_.-]+")
_SLIDES = re.compile(r"[A-Za-z0-9_.*-]+")


class TileKey(NamedTuple):
    """The slide and tile named by a z-stack or focus-result key."""

    slide: str
    row: int
    col: int


def check_name(name: str, what: str = "name") -> str:
    """`name` if it can be one key chunk; ValueError saying why not otherwise."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(
            f"{what} {name!r} is not a valid key chunk (use letters, digits, '_', '-', '.')"
        )
    return name


def _tile(slide: str, row: int, col: int) -> str:
    if row < 0 or col < 0:
        raise ValueError(f"tile ({row}, {col}) must have non-negative row and col")
    return f"{check_name(slide, 'slide')}/{int(row)}/{int(col)}"


def acquire_key(instrument: str) -> str:
    return f"{PREFIX}/instrument/{check_name(instrument, 'instrument')}/acquire"


def laser_key(instrument: str) -> str:
    """Key expression of an instrument's reflection (laser) autofocus queryable."""
    return f"{PREFIX}/instrument/{check_name(instrument, 'instrument')}/laser"


def info_key(instrument: str) -> str:
    return f"{PREFIX}/instrument/{check_name(instrument, 'instrument')}/info"


def frames_key(instrument: str) -> str:
    return f"{PREFIX}/instrument/{check_name(instrument, 'instrument')}/frames"


def zstack_key(slide: str, row: int, col: int) -> str:
    return f"{PREFIX}/zstack/{_tile(slide, row, col)}"


def zframe_key(slide: str, row: int, col: int) -> str:
    return f"{PREFIX}/zframe/{_tile(slide, row, col)}"


def focus_key(slide: str, row: int, col: int) -> str:
    return f"{PREFIX}/focus/{_tile(slide, row, col)}"


def phase_key(slide: str, row: int, col: int) -> str:
    return f"{PREFIX}/phase/{_tile(slide, row, col)}"


def phase_truth_key(instrument: str, slide: str, row: int, col: int) -> str:
    instrument = check_name(instrument, "instrument")
    return f"{PREFIX}/eval/phase/{instrument}/{_tile(slide, row, col)}"


def phase_truth_pattern(instrument: str) -> str:
    """Key expression of the phase-truth queryable of an instrument (every slide and tile)."""
    return f"{PREFIX}/eval/phase/{check_name(instrument, 'instrument')}/*/*/*"


def truth_key(instrument: str, slide: str) -> str:
    instrument = check_name(instrument, "instrument")
    return f"{PREFIX}/eval/truth/{instrument}/{check_name(slide, 'slide')}"


def truth_pattern(instrument: str) -> str:
    """Key expression of the truth queryable of an instrument (all its slides)."""
    return f"{PREFIX}/eval/truth/{check_name(instrument, 'instrument')}/*"


def bench_key(name: str) -> str:
    """``focustrack/v1/bench/{name}``: traffic of the benches only."""
    return f"{PREFIX}/bench/{check_name(name, 'bench key')}"


def slides_chunk(slides: str) -> str:
    """The key chunk matching the slides `slides` names: a slide's name in which ``*``
    stands for any characters (``scanner-1-*``; ``*`` alone: every slide; Zenoh's own
    ``$*`` is taken too). ValueError saying why if it cannot be one chunk."""
    glob = re.sub(r"\$?\*+", "*", slides)
    if not _SLIDES.fullmatch(glob):
        raise ValueError(
            f"slides {slides!r} is not a slide name or pattern (letters, digits, '_', '-', "
            "'.', and '*' for any characters)"
        )
    return glob if glob == "*" else glob.replace("*", "$*")


def zstack_pattern(slides: str | None = None) -> str:
    """Key expression matching the stacks of the slides `slides` names (`slides_chunk`: one
    slide, or a pattern) or of every slide when None."""
    return f"{PREFIX}/zstack/{'*' if slides is None else slides_chunk(slides)}/*/*"


def zframe_pattern(slides: str | None = None) -> str:
    """Key expression matching the frames of the stacks of the slides `slides` names
    (`slides_chunk`: one slide, or a pattern) or of every slide when None."""
    return f"{PREFIX}/zframe/{'*' if slides is None else slides_chunk(slides)}/*/*"


def focus_pattern(slide: str | None = None) -> str:
    """Key expression matching the focus results of one slide (or of every slide when None)."""
    return f"{PREFIX}/focus/{'*' if slide is None else check_name(slide, 'slide')}/*/*"


def phase_pattern(slide: str | None = None) -> str:
    """Key expression matching the phase results of one slide (or of every slide when None)."""
    return f"{PREFIX}/phase/{'*' if slide is None else check_name(slide, 'slide')}/*/*"


def alive_key(service: AliveService, slides: str, zid: str) -> str:
    """The liveliness token of a `service` ("focus" or "phase") reading the stacks of the
    slides `slides` names (`slides_chunk`), its session's id `zid`."""
    return f"{PREFIX}/alive/{service}/{slides_chunk(slides)}/{check_name(zid, 'zid')}"


def alive_pattern(service: AliveService, slide: str) -> str:
    """Key expression matching the tokens of the `service`s ("focus" or "phase") that read
    slide `slide` (a token's ``*`` or ``$*`` matches it too)."""
    return f"{PREFIX}/alive/{service}/{check_name(slide, 'slide')}/*"


def _parse_tile_key(key: str, kind: str) -> TileKey:
    parts = str(key).split("/")
    if len(parts) != 6 or "/".join(parts[:3]) != f"{PREFIX}/{kind}":
        raise ValueError(f"{key!r} is not a {PREFIX}/{kind}/{{slide}}/{{row}}/{{col}} key")
    slide, row, col = parts[3:]
    if not (row.isdigit() and col.isdigit()):
        raise ValueError(f"{key!r}: row and col must be non-negative integers")
    return TileKey(check_name(slide, "slide"), int(row), int(col))


def parse_zstack_key(key: str) -> TileKey:
    """(slide, row, col) of a ``focustrack/v1/zstack/{slide}/{row}/{col}`` key."""
    return _parse_tile_key(key, "zstack")


def parse_zframe_key(key: str) -> TileKey:
    """(slide, row, col) of a ``focustrack/v1/zframe/{slide}/{row}/{col}`` key."""
    return _parse_tile_key(key, "zframe")


def parse_focus_key(key: str) -> TileKey:
    """(slide, row, col) of a ``focustrack/v1/focus/{slide}/{row}/{col}`` key."""
    return _parse_tile_key(key, "focus")


def parse_phase_key(key: str) -> TileKey:
    """(slide, row, col) of a ``focustrack/v1/phase/{slide}/{row}/{col}`` key."""
    return _parse_tile_key(key, "phase")
