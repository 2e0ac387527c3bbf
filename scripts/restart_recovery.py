"""How soon a scan goes on after its router, its focus service or its phase service
restarts with a result in flight (docs/benchmarks.md).

    .venv/bin/python scripts/restart_recovery.py [--service router|focus|phase]
        [--runs 3] [--json OUT]

Each run starts the demo's stack on loopback with the router in a process of its own
(`LocalStack(router_process=True)`; a 4x4 slide of 512 px tiles) and `focustrack scan`
on it with the default timeouts (a focus or phase result is awaited 15 s); with
`--service phase` the stack has a phase service and the scan takes a phase stack of each
tile (`--phase`). As soon as the scan's fourth acquisition is logged (its stack's focus
result then still on its way; with `--service phase`, its first phase) the `--service` is
killed (SIGKILL) and started again DOWN_S later. Printed per run, in seconds: from the
restart to the second acquisition after the kill (the first may have been made before
it), and to the scan's end; and the tiles left without phase. Before a scan noticed the
lost link (the router) or the lost service (its liveliness token) it waited out the
result's timeout: about 10 s to that acquisition instead of about 3.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from focustrack.local_stack import LocalStack
from focustrack_scheduler import outputs

DOWN_S = 5.0
KILL_AFTER = 4  # acquisitions logged
INSTRUMENT_ARGS = ["--seed", "5", "--rows", "4", "--cols", "4", "--width", "512", "--height", "512"]


def logged(out_dir: Path, event: str) -> int:
    """Entries `event` ("acquired", "phase") in the scan's log so far."""
    path = out_dir / outputs.LOG_FILE
    return path.read_text().count(f'"event": "{event}"') if path.exists() else 0


def acquisitions(out_dir: Path) -> int:
    return logged(out_dir, "acquired")


#: What the scan logs when it takes a focus result for lost, by the service restarted (a
#: phase service's loss shows in the tiles left without phase).
NOTICED = {"router": "the bus went down and is back", "focus": "its focus service went"}
SERVICES = ("router", "focus", "phase")


def one_run(work: Path, service: str) -> dict[str, float]:
    """One scan with `service` restarted under it; seconds from the restart."""
    phase = service == "phase"
    with LocalStack(work / "stack", INSTRUMENT_ARGS, router_process=True, phase=phase) as stack:
        out_dir = work / "scan"
        command = [
            sys.executable, "-m", "focustrack", "scan", "--no-progress",
            "--estimator", stack.estimator_url, "--connect", stack.endpoint,
            "--result-key-file", str(stack.result_key_file), "--out", str(out_dir),
            *(["--phase"] if phase else []),
        ]  # fmt: skip
        scan = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
            env=os.environ | {"PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        while logged(out_dir, "phase") < 1 if phase else acquisitions(out_dir) < KILL_AFTER:
            if scan.poll() is not None:
                raise RuntimeError(f"the scan ended early: {scan.communicate()[1]}")
            time.sleep(0.002)
        killed_at = acquisitions(out_dir)
        stack.services[service].kill()
        time.sleep(DOWN_S)
        stack.restart(service)
        restarted_s = time.monotonic()
        while acquisitions(out_dir) < killed_at + 2 and scan.poll() is None:
            time.sleep(0.01)
        next_s = time.monotonic() - restarted_s
        _, stderr = scan.communicate(timeout=300)
        if scan.returncode != 0:
            raise RuntimeError(f"the scan failed: {stderr[-2000:]}")
        figures: dict[str, float] = {
            "to_second_acquisition_s": round(next_s, 2),
            "to_scan_end_s": round(time.monotonic() - restarted_s, 2),
        }
        if phase:
            report = json.loads((out_dir / outputs.REPORT).read_text())
            figures["tiles_without_phase"] = report["tiles_imaged"] - report["tiles_with_phase"]
        else:
            figures["lost_results_noticed"] = stderr.count(NOTICED[service])
        return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--service", choices=SERVICES, default="router", help="what restarts (router)"
    )
    parser.add_argument("--runs", type=int, default=3, help="scans, each with a restart (3)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the runs as JSON")
    args = parser.parse_args()
    runs = []
    for run in range(args.runs):
        with tempfile.TemporaryDirectory() as work:
            runs.append(one_run(Path(work), args.service))
        print(f"run {run + 1}/{args.runs}: {runs[-1]}", flush=True)
    if args.json:
        report = {"service": args.service, "down_s": DOWN_S, "runs": runs}
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
