"""`focustrack bench chaos`: scans on loopback while services die and a rogue peer lies.

The stack of `focustrack demo` (the router in a process of its own, the instrument, the
focus service, the estimator) scans the slide again and again, at least `--scans` times
and for as long as the fault script runs, while:

- a fault script, seeded (`--seed`), kills (SIGKILL) the router, the focus service or
  the estimator, chosen at random, waits a random outage of up to `--down-max-s`, and
  starts it again: at most `--faults` times and not after `--duration-s`;
- a rogue peer answers every stack it sees on the bus with a wrong focus result (the
  top of the stack plus `RoguePeer.OFFSET_UM`), half of them untagged and half with a
  forged tag, before the focus service can answer.

A scan that stops all the same (a service gone longer than its retry policy allows) is
run again on its folder, which resumes it. Then the hostile REST requests of
`focustrack.bench.hostile` (`fire(estimator_url, focus_url)`, where that module exists;
otherwise the step is skipped and the report says so) are fired at the estimator and
the focus service, and the attacks of `focustrack.bench.bus_attacks` on the bus, from a
peer that holds no key:

- replay: a scan of the slide while the peer records its focus results; the slide's
  focus moves by `--replay-offset-um` (the instrument is restarted with it); a second
  scan while the peer re-publishes each recorded result for the stack of the same tile
  and sequence. A measurement whose curve is a replayed result's is one accepted;
- forgery: a scan while the peer publishes, for every stack, frames of its own that
  are sharpest far from the true focus. A measurement at their sharp plane is a forged
  result accepted;
- memory: frames declared at 1 GiB sent part by part and never finished, stacks of
  32 MiB frames that never get their other frames, a FramesRequest naming one frame
  2,000 times. Each service's peak memory is reset before each attack (/proc clear_refs)
  and read when the services are idle again.

The report: scans completed, measurements lost (posted by a scan but not held by the
estimator: must be 0), wrong results accepted (a measurement with the rogue's z: must
be 0), results rejected, the faults, replayed and forged results accepted (must be 0),
the largest resident memory (VmHWM, /proc) of each service over all its processes
before the memory attacks, and under each memory attack (each at most 1 GB); with
`--json OUT`, a chart beside it (OUT with .png): the faults and scans on a time line,
the memory over the run and under the attacks. The exit status is 0 when every figure
that must be 0 is, and no service went over 1 GB.

    focustrack bench chaos [--scans 2 --faults 6 --seed 3] [--json OUT]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import random
import shutil
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import zenoh

from focustrack.arguments import (
    MAX_COUNT,
    count_number,
    finite_number,
    output_file,
    output_folder,
    positive_float,
    seed_number,
    whole_number,
)
from focustrack.bench import bus_attacks
from focustrack.bench.json_report import write_json
from focustrack.local_stack import INSTRUMENT, SLIDE, LocalStack, stop_on_sigterm
from focustrack_core.geometry import MAX_GRID_SIDE
from focustrack_core.v1 import focus_pb2
from focustrack_core.wire import codec, keys
from focustrack_core.wire.rpc import protobuf_encoding
from focustrack_core.wire.session import open_session
from focustrack_estimator import registry
from focustrack_instrument_sim.simulator_options import MAX_FRAME_SIDE_PX
from focustrack_scheduler import outputs
from focustrack_scheduler.clients import InstrumentClient
from focustrack_scheduler.retry import RetryPolicy
from focustrack_scheduler.scan import SCAN_ERRORS, ScanJob, run_scan
from focustrack_scheduler.settings import BEST_KALMAN, ScanOptions

#: The services the fault script may kill.
VICTIMS = ("router", "focus", "estimator")

#: Runs of one scan (the first and its resumptions) before the bench gives it up.
MAX_RUNS = 6

#: Scans at most, however long the fault script runs.
MAX_SCANS = 50

#: The shortest outage of a killed service, s: `--down-max-s` is at least this.
MIN_DOWN_S = 1.0

#: Ride out a minute without a service: the target is a scan that survives any service's
#: restart within a minute.
CHAOS_RETRY = RetryPolicy(instrument_timeout_s=15.0, focus_timeout_s=5.0, instrument_outage_s=60.0)
FOCUS_ATTEMPTS = 12  # x focus_timeout_s: a focus service gone for a minute

#: The most resident memory a service may take, MB, under any attack.
MEMORY_LIMIT_MB = 1024.0

#: What the focus service may hold of a peer's frames, MB: its default budget for frames
#: under way (the stack runs it with the default `--open-frames-mb`).
FOCUS_FRAMES_BUDGET_MB = codec.OPEN_FRAMES_BYTES / 1e6

#: A service is idle again once it uses less than this share of a core.
IDLE_CPU_SHARE = 0.05


class RoguePeer:
    """A peer on the bus that publishes a wrong focus result for every stack it sees.

    On the first frame of each stack it puts a FocusResult for that stack (same tile,
    sequence, frames and nonce, all read from the frame's header) whose best z is the top
    of the stack plus `OFFSET_UM`: every other result untagged, the others with a random
    32-byte tag.
    """

    OFFSET_UM = 5.0

    def __init__(self, endpoint: str, slide: str) -> None:
        self.session = open_session(connect=[endpoint])
        self.sent: dict[tuple[int, int, int], float] = {}  # (row, col, sequence) -> wrong z
        self.n_sent = 0
        self._lock = threading.Lock()
        self._frames = codec.FrameAssembler()
        self._subscriber = self.session.declare_subscriber(
            keys.zframe_pattern(slide), self._on_frame
        )

    def _on_frame(self, sample: zenoh.Sample) -> None:
        try:
            frame = self._frames.add_sample(sample)
        except ValueError:
            return
        if frame is None or frame[0].index != 0:
            return
        frame_header = frame[0]
        stack = frame_header.stack
        wrong_z_um = stack.z_um[-1] + self.OFFSET_UM
        n = len(stack.z_um)
        result = focus_pb2.FocusResult(
            slide=stack.slide,
            row=stack.row,
            col=stack.col,
            sequence=stack.sequence,
            nonce=stack.nonce,
            instrument=stack.instrument,
            metric="brenner",
            z_um=stack.z_um,
            scores=[float(i == n - 1) for i in range(n)],
            best_z_um=wrong_z_um,
            sigma_um=0.01,
        )
        with self._lock:
            forged = self.n_sent % 2 == 1
            self.n_sent += 1
            self.sent[(stack.row, stack.col, stack.sequence)] = wrong_z_um
        self.session.put(
            keys.focus_key(stack.slide, stack.row, stack.col),
            result.SerializeToString(),
            encoding=protobuf_encoding(focus_pb2.FocusResult),
            attachment=os.urandom(32) if forged else None,
        )

    def wrong_accepted(self, log_path: Path) -> int:
        """Measurements in a scan's log that took this peer's wrong z."""
        with self._lock:
            sent = dict(self.sent)
        return bus_attacks.taken(log_path, sent, tolerance_um=1e-6)  # its z to the last digit

    def close(self) -> None:
        self._subscriber.undeclare()
        self.session.close()


def _status_mb(pid: int, field: str) -> float | None:
    """A memory figure of /proc/`pid`/status (VmHWM, VmRSS), MB; None if the process is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def peak_rss_mb(pid: int) -> float | None:
    """The largest resident set of process `pid` so far, MB (VmHWM; None if it is gone)."""
    return _status_mb(pid, "VmHWM")


def rss_mb(pid: int) -> float | None:
    """The resident set of process `pid` now, MB (VmRSS; None if it is gone)."""
    return _status_mb(pid, "VmRSS")


def reset_peak_rss(pid: int) -> None:
    """Start process `pid`'s VmHWM over from its resident set now (Linux >= 4.0; where
    /proc refuses, VmHWM stays the lifetime peak: an upper bound all the same)."""
    with contextlib.suppress(OSError):
        Path(f"/proc/{pid}/clear_refs").write_text("5")


def cpu_s(pid: int) -> float:
    """CPU time process `pid` has used, s (user and system; 0 if it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_until_idle(pids: list[int], timeout_s: float = 60.0, period_s: float = 0.5) -> None:
    """Return once every process in `pids` used under `IDLE_CPU_SHARE` of a core over
    `period_s` (what was sent to it is dealt with), or after `timeout_s`."""
    deadline_s = time.monotonic() + timeout_s
    used_s = [cpu_s(pid) for pid in pids]
    while time.monotonic() < deadline_s:
        time.sleep(period_s)
        now_s = [cpu_s(pid) for pid in pids]
        if all(b - a < IDLE_CPU_SHARE * period_s for a, b in zip(used_s, now_s, strict=True)):
            return
        used_s = now_s


@dataclass
class MemoryWatch:
    """The largest VmHWM seen of each service, over every process it ran in."""

    stack: LocalStack
    peak_mb: dict[str, float] = field(default_factory=dict)

    def sample(self, name: str | None = None) -> None:
        for service_name, service in self.stack.services.items():
            if name not in (None, service_name) or service.process is None:
                continue
            rss_mb = peak_rss_mb(service.process.pid)
            if rss_mb is not None:
                self.peak_mb[service_name] = max(self.peak_mb.get(service_name, 0.0), rss_mb)


@dataclass
class Fault:
    """A kill: when (s since the script started), of which service, the outage chosen, and
    when the restarted service answered again (its start-up included)."""

    at_s: float
    service: str
    down_s: float
    back_at_s: float


class FaultScript:
    """Kills and restarts services at random, on a thread, until told to stop."""

    def __init__(
        self,
        stack: LocalStack,
        memory: MemoryWatch,
        seed: int,
        faults: int,
        duration_s: float,
        gap_max_s: float,
        down_max_s: float,
    ) -> None:
        self.stack, self.memory = stack, memory
        self.rng = random.Random(seed)
        self.max_faults, self.duration_s = faults, duration_s
        self.gap_max_s, self.down_max_s = gap_max_s, down_max_s
        self.done: list[Fault] = []
        self.stop = threading.Event()
        self.started_s = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="chaos", daemon=True)

    def start(self) -> None:
        self.started_s = time.monotonic()
        self._thread.start()

    def _run(self) -> None:
        while len(self.done) < self.max_faults:
            gap_s = self.rng.uniform(0.3 * self.gap_max_s, self.gap_max_s)
            if self.stop.wait(gap_s) or time.monotonic() - self.started_s > self.duration_s:
                return
            victim = self.rng.choice(VICTIMS)
            down_s = self.rng.uniform(MIN_DOWN_S, self.down_max_s)
            at_s = time.monotonic() - self.started_s
            self.memory.sample(victim)
            self.stack.services[victim].kill()
            print(f"[{at_s:6.1f} s] chaos: killed {victim}; down for {down_s:.1f} s", flush=True)
            time.sleep(down_s)
            self.stack.restart(victim)
            back_at_s = time.monotonic() - self.started_s
            print(f"[{back_at_s:6.1f} s] chaos: {victim} is back", flush=True)
            self.done.append(Fault(round(at_s, 1), victim, round(down_s, 1), round(back_at_s, 1)))

    def running(self) -> bool:
        return self._thread.is_alive()

    def join(self) -> None:
        self.stop.set()
        self._thread.join()


def measurements_lost(estimator_url: str, report: dict[str, Any], log_path: Path) -> int:
    """Measurements the scan posted that the estimator does not hold."""
    posted = {
        entry["sequence"]
        for entry in map(json.loads, log_path.read_text().splitlines())
        if entry["event"] == "measured"
    }
    url = f"{estimator_url}/v1/slides/{report['estimator_slide_id']}"
    gone = CHAOS_RETRY.retrying(  # the estimator may be down, killed by the fault script
        CHAOS_RETRY.estimator_outage_s,
        lambda error: isinstance(error, httpx.TransportError),
        "the estimator's slide",
    )
    slide = gone(lambda: httpx.get(url, timeout=10).raise_for_status().json())
    return max(0, len(posted) - int(slide["n_acquisitions"]))


def hostile_requests(stack: LocalStack, memory: MemoryWatch, n_slides: int) -> dict[str, int] | str:
    """Fire `focustrack.bench.hostile`'s requests at the REST services (`n_slides` slides
    created one after another among them): the status each got, or why they were not
    fired. VmHWM keeps each service's peak, so sampling after is exact.
    """
    try:
        hostile = importlib.import_module("focustrack.bench.hostile")
    except ImportError:
        return "skipped: focustrack.bench.hostile is not on this branch"
    focus_url = f"http://127.0.0.1:{stack.focus_port}"
    print(f"hostile REST requests at {stack.estimator_url} and {focus_url}", flush=True)
    statuses: dict[str, int] = hostile.fire(stack.estimator_url, focus_url, n_slides=n_slides)
    memory.sample()
    return statuses


def add_arguments(parser: argparse.ArgumentParser) -> None:
    grid_side = whole_number(1, MAX_GRID_SIDE)
    parser.add_argument("--rows", type=grid_side, default=6, help="tile rows of each slide (6)")
    parser.add_argument("--cols", type=grid_side, default=6, help="tile columns of each slide (6)")
    parser.add_argument(
        "--size",
        type=whole_number(1, MAX_FRAME_SIDE_PX),
        default=128,
        help="frame side in pixels (128)",
    )
    parser.add_argument(
        "--scans",
        type=count_number,
        default=2,
        help="scans at least, one after the other, and more while the faults go on (2)",
    )
    parser.add_argument(
        "--strategy",
        default=BEST_KALMAN,
        choices=list(registry.STRATEGIES),  # a refused one was retried as a stop
        help=f"strategy ({BEST_KALMAN})",
    )
    parser.add_argument(
        "--seed",
        type=seed_number,
        default=3,
        help="seed of the fault script (3: its first kills are the estimator, the focus "
        "service, the router)",
    )
    parser.add_argument(
        "--faults", type=whole_number(0, MAX_COUNT), default=6, help="kills at most (6)"
    )
    parser.add_argument(
        "--duration-s", type=positive_float, default=180.0, help="no kill after this long (180 s)"
    )
    parser.add_argument(
        "--gap-max-s", type=positive_float, default=10.0, help="longest pause between kills (10 s)"
    )
    parser.add_argument(
        "--down-max-s",
        type=finite_number(MIN_DOWN_S),
        default=8.0,
        help=f"longest outage of a killed service, >= {MIN_DOWN_S:g} s (8 s)",
    )
    parser.add_argument(
        "--replay-offset-um",
        type=finite_number(),  # the focus may move either way, or not at all
        default=8.0,
        help="the slide's focus moves by this much between the recorded scan and the one "
        "the results are replayed into (8 um)",
    )
    parser.add_argument(
        "--attack-sizes",
        choices=sorted(bus_attacks.ATTACK_SIZES),
        default="issue",
        help="what the memory attacks send: 'issue', the attacker's gigabytes (default), or "
        "'small', megabytes for a quick run",
    )
    parser.add_argument(
        "--hostile-slides",
        type=count_number,
        default=2000,
        help="slides the hostile REST requests create one after another (2000; a quick "
        "run: a dozen)",
    )
    parser.add_argument("--out", type=output_folder, default=Path("out/chaos"), help="work folder")
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the report as JSON")


def run(args: argparse.Namespace) -> int:
    instrument_args = [
        "--seed", "1", "--slides", "1", "--rows", str(args.rows),
        "--cols", str(args.cols), "--width", str(args.size), "--height", str(args.size),
    ]  # fmt: skip
    stop_on_sigterm()  # so that the stack's processes are stopped on the way out
    args.out.mkdir(parents=True, exist_ok=True)
    for stale in args.out.glob("estimator.sqlite*"):
        stale.unlink()
    started_s = time.perf_counter()
    try:
        with LocalStack(args.out, instrument_args, router_process=True) as stack:
            assert stack.session is not None
            print(f"stack ready in {time.perf_counter() - started_s:.1f} s; router "
                  f"{stack.endpoint}, estimator {stack.estimator_url}", flush=True)  # fmt: skip
            memory = MemoryWatch(stack)
            rogue = RoguePeer(stack.endpoint, SLIDE)
            chaos = FaultScript(
                stack,
                memory,
                args.seed,
                args.faults,
                args.duration_s,
                args.gap_max_s,
                args.down_max_s,
            )
            chaos.start()
            scans: list[dict[str, Any]] = []
            try:
                while len(scans) < args.scans or (chaos.running() and len(scans) < MAX_SCANS):
                    name = f"scan-{len(scans)}"
                    figures, log_path = scan_once(stack, args, name, memory)
                    figures["wrong_results_accepted"] = rogue.wrong_accepted(log_path)
                    figures["finished_at_s"] = round(time.monotonic() - chaos.started_s, 1)
                    _say(name, figures)
                    scans.append(figures)
            finally:
                chaos.join()
                rogue.close()
            memory.sample()
            hostile = hostile_requests(stack, memory, args.hostile_slides)
            print(f"hostile REST requests: {json.dumps(hostile)}", flush=True)
            memory.sample()
            replay = replay_attack(stack, args, memory)
            forgery = forgery_attack(stack, args, memory)
            memory.sample()  # the run's peaks: before the memory attacks, which reset them
            with open_session(connect=[stack.endpoint]) as attacker:
                attacks = memory_attacks(
                    stack, attacker, bus_attacks.ATTACK_SIZES[args.attack_sizes]
                )
    except KeyboardInterrupt:
        print("focustrack bench chaos: interrupted; services stopped", file=sys.stderr)
        return 130
    attack_scans = [replay["recorded_scan"], replay["replayed_scan"], forgery["scan"]]
    report = {
        "scans": scans,
        "scans_completed": sum(scan["completed"] for scan in scans),
        "measurements_lost": sum(scan["measurements_lost"] for scan in scans),
        "wrong_results_accepted": sum(scan["wrong_results_accepted"] for scan in scans),
        "focus_results_rejected": sum(scan["focus_results_rejected"] for scan in scans),
        "rogue_results_sent": rogue.n_sent,
        "faults": [vars(fault) for fault in chaos.done],
        "hostile_requests": hostile,
        "replayed_results_accepted": replay["replayed_results_accepted"],
        "forged_results_accepted": forgery["forged_results_accepted"],
        "replay": replay,
        "forgery": forgery,
        "peak_rss_mb": {name: round(mb, 1) for name, mb in sorted(memory.peak_mb.items())},
        "memory_attacks": attacks,
        "wall_time_s": round(time.perf_counter() - started_s, 1),
    }
    print(summary(report))
    if args.json is not None:
        write_json(args.json, report)
        chart(report, args.json.with_suffix(".png"))
        print(f"wrote {args.json}, {args.json.with_suffix('.png')}")
    ok = (
        all(scan["completed"] and scan["measurements_lost"] == 0 for scan in scans + attack_scans)
        and report["wrong_results_accepted"] == 0
        and report["replayed_results_accepted"] == 0
        and report["forged_results_accepted"] == 0
        and all(
            mb <= MEMORY_LIMIT_MB
            for attack in attacks.values()
            for mb in attack["peak_mb"].values()
        )
        and all(_focus_growth_mb(attack) <= FOCUS_FRAMES_BUDGET_MB for attack in attacks.values())
    )
    return 0 if ok else 1


def scan_once(
    stack: LocalStack, args: argparse.Namespace, name: str, memory: MemoryWatch
) -> tuple[dict[str, Any], Path]:
    """One scan in folder `name` of the work folder, resumed there after a stop; its
    figures and its log."""
    assert stack.session is not None
    scan_dir = args.out / name
    shutil.rmtree(scan_dir, ignore_errors=True)  # a fresh scan each run of the bench
    job = ScanJob(
        request=ScanOptions.defaults(focus_attempts=FOCUS_ATTEMPTS).request(
            INSTRUMENT, SLIDE, args.strategy
        ),
        estimator_url=stack.estimator_url,
        out_dir=scan_dir,
        retry=CHAOS_RETRY,
        progress=False,
        label=f"chaos {name}",
        trust=stack.trust,
    )
    report: dict[str, Any] | None = None
    runs = 0
    while report is None and runs < MAX_RUNS:
        runs += 1
        try:
            report = run_scan(stack.session, job)
        except SCAN_ERRORS as error:
            print(f"{name}: stopped ({error}); resuming it", flush=True)
        memory.sample()
    log_path = scan_dir / outputs.LOG_FILE
    figures: dict[str, Any] = {"completed": report is not None, "runs": runs}
    if report is not None:
        figures |= {
            "measurements_lost": measurements_lost(stack.estimator_url, report, log_path),
            "focus_results_rejected": report["focus_results_rejected"],
            "in_focus_fraction": report["in_focus_fraction"],
            "mae_um": report["mae_um"],
            "images_per_tile": report["images_per_tile"],
        }
    else:
        figures |= {"measurements_lost": args.rows * args.cols, "focus_results_rejected": 0}
    return figures, log_path


def _say(name: str, figures: dict[str, Any]) -> None:
    done = "complete" if figures["completed"] else "NOT complete"
    print(f"{name}: {done} in {figures['runs']} run(s); {json.dumps(figures)}", flush=True)


def replay_attack(
    stack: LocalStack, args: argparse.Namespace, memory: MemoryWatch
) -> dict[str, Any]:
    """A scan recorded by a peer; the slide's focus moved; a scan the peer replays it into."""
    with bus_attacks.PeerProcess(stack.endpoint, bus_attacks.ResultReplay, SLIDE) as replay:
        replay.call("record")
        try:
            recorded, _ = scan_once(stack, args, "replay-recorded", memory)
        finally:
            replay.call("stop")
        _say("replay: the recorded scan", recorded)
        n_recorded = replay.call("n_captured")
        print(f"replay: {n_recorded} results recorded; the slide's focus moves by "
              f"{args.replay_offset_um:g} um", flush=True)  # fmt: skip
        memory.sample("instrument")
        stack.restart_with("instrument", ["--z-offset-um", str(args.replay_offset_um)])
        replay.call("replay")
        try:
            replayed, log_path = scan_once(stack, args, "replay", memory)
        finally:
            replay.call("stop")
        accepted = replay.call("accepted", log_path)
        n_replayed = replay.call("n_replayed")
    replayed["replayed_results_accepted"] = accepted
    _say("replay: the scan after the move", replayed)
    return {
        "offset_um": args.replay_offset_um,
        "results_recorded": n_recorded,
        "results_replayed": n_replayed,
        "replayed_results_accepted": accepted,
        "recorded_scan": recorded,
        "replayed_scan": replayed,
    }


def forgery_attack(
    stack: LocalStack, args: argparse.Namespace, memory: MemoryWatch
) -> dict[str, Any]:
    """A scan while a peer publishes forged frames for every stack."""
    assert stack.session is not None
    truth_um = InstrumentClient(stack.session, INSTRUMENT).truth_um(SLIDE)
    peer = bus_attacks.PeerProcess(stack.endpoint, bus_attacks.FrameForger, SLIDE, truth_um)
    with peer as forger:
        figures, log_path = scan_once(stack, args, "forgery", memory)
        accepted = forger.call("accepted", log_path)
        n_forged = forger.call("n_forged")
    figures["forged_results_accepted"] = accepted
    _say("forgery: the scan", figures)
    return {"stacks_forged": n_forged, "forged_results_accepted": accepted, "scan": figures}


def memory_attacks(
    stack: LocalStack,
    attacker: zenoh.Session,
    sizes: bus_attacks.MemoryAttackSizes = bus_attacks.ISSUE_SIZES,
) -> dict[str, dict[str, Any]]:
    """Each memory attack: what it sent, and each service's resident memory before it
    (VmRSS) and its peak from then until the services are idle again (VmHWM), MB."""
    attacks = {
        "big-frames": lambda: bus_attacks.big_frames(attacker, sizes),
        "incomplete-stacks": lambda: bus_attacks.incomplete_stacks(attacker, sizes),
        "repeated-frames-request": lambda: bus_attacks.repeated_frames_request(
            attacker, INSTRUMENT, SLIDE, sizes
        ),
    }
    results: dict[str, dict[str, Any]] = {}
    for name, attack in attacks.items():
        pids = {
            service_name: service.process.pid
            for service_name, service in stack.services.items()
            if service.process is not None
        }
        for pid in pids.values():
            reset_peak_rss(pid)
        before = {service_name: rss_mb(pid) for service_name, pid in pids.items()}
        started_s = time.perf_counter()
        sent = attack()
        wait_until_idle(list(pids.values()))
        peak = {service_name: peak_rss_mb(pid) for service_name, pid in pids.items()}
        results[name] = {
            "sent": sent,
            "baseline_mb": {key: round(mb, 1) for key, mb in before.items() if mb is not None},
            "peak_mb": {key: round(mb, 1) for key, mb in peak.items() if mb is not None},
        }
        print(f"memory attack {name} ({time.perf_counter() - started_s:.1f} s): "
              f"{json.dumps(results[name])}", flush=True)  # fmt: skip
    return results


def chart(report: dict[str, Any], out: Path) -> None:
    """The faults and scans on a time line; each service's peak memory over the run and
    under each memory attack, against 1 GB."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (timeline, memory, attacked) = plt.subplots(
        1, 3, figsize=(15, 4.2), gridspec_kw={"width_ratios": [2, 1, 1.4]}
    )
    rows = {name: index for index, name in enumerate(VICTIMS)}
    for fault in report["faults"]:
        row, at_s = rows[fault["service"]], fault["at_s"]
        timeline.barh(row, fault["back_at_s"] - at_s, left=at_s, color="tab:orange")
        timeline.barh(row, fault["down_s"], left=at_s, color="tab:red")
    for scan in report["scans"]:
        colour = "tab:green" if scan["completed"] else "black"
        timeline.axvline(scan["finished_at_s"], color=colour, ls=":", lw=1)
    timeline.set_yticks(list(rows.values()), list(rows))
    timeline.set_xlabel(
        "s since the fault script started (red: down; orange: starting again; dotted: a scan ended)"
    )
    timeline.set_title(
        f"{report['scans_completed']} scans complete, {report['measurements_lost']} "
        f"measurements lost, {report['wrong_results_accepted']} wrong results taken",
        fontsize=10,
    )
    names = list(report["peak_rss_mb"])
    memory.bar(names, [report["peak_rss_mb"][name] for name in names])
    memory.axhline(MEMORY_LIMIT_MB, color="red", ls="--", label="1 GB")
    memory.set_ylabel("peak resident memory, MB")
    memory.set_title("faults, rogue, REST, replay, forgery", fontsize=10)
    memory.legend()
    attacks = report["memory_attacks"]
    width = 0.8 / max(1, len(attacks))
    for index, (attack, figures) in enumerate(attacks.items()):
        where = [names.index(name) + (index - (len(attacks) - 1) / 2) * width for name in names]
        peaks = [figures["peak_mb"].get(name, 0.0) for name in names]
        baselines = [figures["baseline_mb"].get(name, 0.0) for name in names]
        attacked.bar(where, peaks, width, label=attack)
        attacked.scatter(where, baselines, color="black", marker="_", zorder=3)
    attacked.set_xticks(range(len(names)), names)
    attacked.axhline(MEMORY_LIMIT_MB, color="red", ls="--")
    attacked.set_title("under the memory attacks (bar: peak; dash: before)", fontsize=10)
    attacked.legend(fontsize=8)
    fig.suptitle(
        f"replayed results taken: {report['replayed_results_accepted']} (of "
        f"{report['replay']['results_replayed']} replayed); forged results taken: "
        f"{report['forged_results_accepted']} ({report['forgery']['stacks_forged']} stacks "
        "forged); both must be 0",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def summary(report: dict[str, Any]) -> str:
    replay, forgery = report["replay"], report["forgery"]
    lines = [
        f"scans completed:        {report['scans_completed']} of {len(report['scans'])}",
        f"measurements lost:      {report['measurements_lost']} (must be 0)",
        f"wrong results accepted: {report['wrong_results_accepted']} (must be 0; the rogue "
        f"sent {report['rogue_results_sent']})",
        f"results rejected:       {report['focus_results_rejected']}",
        f"faults:                 {', '.join(f['service'] for f in report['faults']) or 'none'}",
        f"hostile REST requests:  {report['hostile_requests']}",
        f"replayed results taken: {report['replayed_results_accepted']} (must be 0; "
        f"{replay['results_replayed']} replayed of {replay['results_recorded']} recorded; "
        f"MAE after the {replay['offset_um']:g} um move {_um(replay['replayed_scan'])})",
        f"forged results taken:   {report['forged_results_accepted']} (must be 0; "
        f"{forgery['stacks_forged']} stacks forged; MAE {_um(forgery['scan'])})",
        "peak RSS (MB):          "
        + ", ".join(f"{name} {mb:.0f}" for name, mb in report["peak_rss_mb"].items()),
    ]
    for attack, figures in report["memory_attacks"].items():
        lines.append(
            f"  under {attack} (at most {MEMORY_LIMIT_MB:.0f}; the focus service's growth "
            f"{_focus_growth_mb(figures):.0f}, at most {FOCUS_FRAMES_BUDGET_MB:.0f}): "
            + ", ".join(
                f"{name} {mb:.0f} (from {figures['baseline_mb'].get(name, 0.0):.0f})"
                for name, mb in figures["peak_mb"].items()
            )
        )
    return "\n".join(lines)


def _focus_growth_mb(attack: dict[str, Any]) -> float:
    """How much the focus service's resident memory grew under a memory attack, MB."""
    return max(0.0, float(attack["peak_mb"]["focus"] - attack["baseline_mb"]["focus"]))


def _um(scan: dict[str, Any]) -> str:
    mae_um = scan.get("mae_um")
    return "n/a" if mae_um is None else f"{mae_um:.3f} um"
