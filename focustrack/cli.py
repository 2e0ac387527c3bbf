"""The `focustrack` command: one entry point, a subcommand per job.

Each subcommand lives in its own module. A service's module (and the scan's)
provides ``Settings``, its one settings model (`focustrack_core.settings`: flags,
environment and settings file alike), and ``run(settings: Settings) -> int``, as its
own console script (`focustrack-estimator`, ...) uses them; any other module
provides ``add_arguments(parser: argparse.ArgumentParser) -> None`` and
``run(args: argparse.Namespace) -> int``. Only the chosen module is imported,
so `focustrack bench accuracy` does not pay for starting Zenoh or FastAPI.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from focustrack_core.settings import ServiceSettings, parse

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "bench accuracy": (
        "focustrack.bench.accuracy",
        "replay focus maps through every strategy; accuracy, images and scan time",
    ),
    "bench rescan": (
        "focustrack.bench.rescan",
        "a slide scanned twice with drift: the second pass learning from the first",
    ),
    "bench drift": (
        "focustrack.bench.drift",
        "focus drifting in time during a scan: the time state, revisits, against kf-2d-lean",
    ),
    "bench tune": (
        "focustrack.bench.tune",
        "choose the Kalman strategies' defaults on training seeds",
    ),
    "bench focus": ("focustrack.bench.focus", "focus-metric accuracy and speed"),
    "bench scale": (
        "focustrack.bench.scale",
        "cost per tile, final map, memory and restarts as the slide grows",
    ),
    "bench api": ("focustrack.bench.api", "estimator REST latency and throughput"),
    "bench instrument": (
        "focustrack.bench.instrument",
        "render and publish speed of the simulated microscope",
    ),
    "bench transport": (
        "focustrack.bench.transport",
        "Zenoh frame streaming over TCP and shared memory against memcpy, and focus latency",
    ),
    "bench startup": (
        "focustrack.bench.startup",
        "seconds from exec to the first answer of each service, of `scan --help` and of a bare "
        "FastAPI app (the floor)",
    ),
    "bench chaos": (
        "focustrack.bench.chaos",
        "scans while the router and services are killed at random and a rogue peer lies",
    ),
    "bench phase": (
        "focustrack.bench.phase",
        "phase from a through-focus stack: the sparse ACEKF against the paper and two baselines",
    ),
    "bench mmcore": (
        "focustrack.bench.mmcore",
        "ms per plane of the MMCore backend's stacks against bare MMCore calls, snapped and "
        "sequenced",
    ),
    "bench slide": (
        "focustrack.bench.slide",
        "virtual tissue slides (empty glass, dust, folds, tilt) scanned by every strategy",
    ),
    "serve instrument": (
        "focustrack_instrument_sim.service",
        "a microscope on Zenoh: the simulator, or one through Micro-Manager (--backend mmcore)",
    ),
    "serve focus": ("focustrack_focus.service", "the focus service (Zenoh and REST)"),
    "serve estimator": ("focustrack_estimator.service", "the estimator REST service"),
    "serve phase": ("focustrack_phase.service", "the phase service (REST and Zenoh)"),
    "scan": ("focustrack_scheduler.scan", "scan one slide through the services"),
    "demo": ("focustrack.demo", "embedded stack: scan a simulated slide"),
    "focus calibrate": (
        "focustrack.focus_calibrate",
        "a microscope profile (each focus metric's constants) from labelled curves or stacks",
    ),
    "bus secrets": (
        "focustrack.bus_secrets",
        "certificates, passwords and Zenoh configs of an authenticated bus",
    ),
}


def _usage(group: str = "") -> str:
    """The commands (those of `group`, the first word of several: ``bench``), a line each."""
    names = [name for name in COMMANDS if name.startswith(f"{group} ")] or list(COMMANDS)
    width = max(len(name) for name in names)
    command = f"{group} COMMAND" if group else "COMMAND"
    lines = [f"usage: focustrack {command} [options]", "", "commands:"]
    lines += [f"  {name:<{width}}  {COMMANDS[name][1]}" for name in names]
    lines += ["", "`focustrack COMMAND --help` shows the options of one command."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the command `argv` names (the process's own by default); its exit status. Ctrl-C
    before the command has a handler of its own (in its imports, its parsing) is status
    130 with one line, not a traceback."""
    try:
        return _main(sys.argv[1:] if argv is None else argv)
    except KeyboardInterrupt:
        print("focustrack: interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str]) -> int:
    for n_words in (2, 1):
        name = " ".join(argv[:n_words])
        if name in COMMANDS:
            module_name, text = COMMANDS[name]
            module = importlib.import_module(module_name)
            parser = argparse.ArgumentParser(prog=f"focustrack {name}", description=text)
            settings_cls = getattr(module, "Settings", None)
            if isinstance(settings_cls, type) and issubclass(settings_cls, ServiceSettings):
                settings_cls.add_arguments(parser)
                return module.run(parse(parser, settings_cls, argv[n_words:]))
            module.add_arguments(parser)
            return module.run(parser.parse_args(argv[n_words:]))
    group = argv[0] if argv and any(name.startswith(f"{argv[0]} ") for name in COMMANDS) else ""
    if not argv or argv[0] in ("-h", "--help") or (group and argv[1:2] in ([], ["-h"], ["--help"])):
        print(_usage(group))  # `focustrack bench`: the benchmarks
        return 0
    words = " ".join(word for word in argv[:2] if not word.startswith("-"))
    print(f"{_usage(group)}\n\nfocustrack: error: unknown command {words!r}", file=sys.stderr)
    return 2
