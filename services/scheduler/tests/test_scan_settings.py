"""`focustrack scan`'s settings: today's flags, variables and defaults, from one model."""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from focustrack_client import models as api
from focustrack_core.settings import parse
from focustrack_core.wire.session import free_port
from focustrack_scheduler import outputs, scan
from focustrack_scheduler.engine import ScanRefusedError
from focustrack_scheduler.outputs import MosaicFormat
from focustrack_scheduler.realign import Realign
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.retry import RetryPolicy
from focustrack_scheduler.settings import BEST_KALMAN, TOKEN_ENV, ScanOptions, ScanSettings

#: Every option of `focustrack scan` (flag -> default): those before its settings model,
#: and the phase stacks'.
OPTIONS = {
    "bus_timeout_s": 30.0,
    "estimator": "http://127.0.0.1:8100",
    "token": None,
    "connect": None,
    "listen": None,
    "mode": None,
    "zenoh_config": None,
    "shared_memory": 0,
    "instrument": "sim",
    "slide": "slide-0",
    "strategy": BEST_KALMAN,
    "param": [],
    "out": Path("out/scan"),
    "live_port": None,
    "live_host": "127.0.0.1",
    "first_pass": None,
    "lateral_tiles": 4,
    "lateral_max_um": 10.0,
    "frame_check_ratio": 0.94,
    "start_z_um": 0.0,
    "start_sigma_um": 10.0,
    "noise_sigma_um": 0.1,
    "k_sigma": api.ZRangePolicy().k_sigma,
    "z_step_um": api.ZRangePolicy().z_step_um,
    "min_frames": api.ZRangePolicy().min_frames,
    "max_frames": api.ZRangePolicy().max_frames,
    "instrument_timeout_s": RetryPolicy().instrument_timeout_s,
    "instrument_outage_s": RetryPolicy().instrument_outage_s,
    "focus_timeout_s": RetryPolicy().focus_timeout_s,
    "focus_attempts": 5,
    "estimator_outage_s": RetryPolicy().estimator_outage_s,
    "phase": False,
    "phase_planes": 11,
    "phase_step_um": None,
    "phase_timeout_s": RetryPolicy().phase_timeout_s,
    "phase_in_flight": RetryPolicy().phase_in_flight,
    "mosaic_format": MosaicFormat.OME_ZARR,
    "no_progress": False,
    "result_key_file": None,
    "metrics_port": None,
    "metrics_host": "127.0.0.1",
    "otlp_endpoint": None,
}


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [*ScanSettings.model_fields, "settings"]:
        monkeypatch.delenv(ScanSettings.variable(name), raising=False)
    monkeypatch.delenv(TOKEN_ENV, raising=False)


def settings(*argv: str) -> ScanSettings:
    parser = argparse.ArgumentParser()
    ScanSettings.add_arguments(parser)
    return parse(parser, ScanSettings, list(argv))


def test_every_option_keeps_its_flag_variable_and_default() -> None:
    parser = argparse.ArgumentParser()
    ScanSettings.add_arguments(parser)
    flags = {flag for action in parser._actions for flag in action.option_strings}
    assert {"--" + name.replace("_", "-") for name in OPTIONS} <= flags
    assert set(ScanSettings.model_fields) == set(OPTIONS)
    assert {name: getattr(settings(), name) for name in OPTIONS} == OPTIONS
    assert ScanSettings.variable("no_progress") == "FOCUSTRACK_SCAN_NO_PROGRESS"
    assert settings().endpoints() == (["tcp/127.0.0.1:7447"], [])


def test_flags_over_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FOCUSTRACK_SCAN_K_SIGMA", "3.5")
    monkeypatch.setenv("FOCUSTRACK_SCAN_NO_PROGRESS", "1")
    monkeypatch.setenv("FOCUSTRACK_SCAN_FOCUS_TIMEOUT_S", "4")
    got = settings("--focus-timeout-s", "5", "--mosaic-format", "ome-tiff", "--live-port", "0")
    assert (got.k_sigma, got.no_progress, got.focus_timeout_s) == (3.5, True, 5.0)
    assert got.mosaic_format is MosaicFormat.OME_TIFF and got.live_port == 0
    assert got.retry() == RetryPolicy(focus_timeout_s=5.0)
    assert got.scan_request().policy.k_sigma == 3.5


def test_param_takes_name_value_items_whose_values_may_hold_commas(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    got = settings("--param", "prior_map_um=[1.0, 2.0]", "--param", "label=a,b", "--param", "n=3")
    assert got.params == {"prior_map_um": [1.0, 2.0], "label": "a,b", "n": 3}
    assert got.scan_request().params == got.params
    monkeypatch.setenv("FOCUSTRACK_SCAN_PARAM", "gain=0.5")
    assert settings().params == {"gain": 0.5}


def test_the_token_defaults_to_the_estimators_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(TOKEN_ENV, "from-estimator")
    assert settings().token == "from-estimator"
    monkeypatch.setenv("FOCUSTRACK_SCAN_TOKEN", "from-scan")
    assert settings().token == "from-scan"
    assert settings("--token", "from-flag").token == "from-flag"


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (
            ["--param", "no-equals"],
            "--param (FOCUSTRACK_SCAN_PARAM): takes NAME=VALUE",
        ),
        (["--live-port", "70000"], "--live-port (FOCUSTRACK_SCAN_LIVE_PORT)"),
        (["--focus-attempts", "0"], "--focus-attempts (FOCUSTRACK_SCAN_FOCUS_ATTEMPTS)"),
        (["--start-sigma-um", "0"], "--start-sigma-um (FOCUSTRACK_SCAN_START_SIGMA_UM)"),
        (["--k-sigma", "0"], "--k-sigma (FOCUSTRACK_SCAN_K_SIGMA): Input should be greater"),
        (["--mosaic-format", "png"], "invalid choice: 'png'"),
        (["--lateral-max-um", "0"], "--lateral-max-um (FOCUSTRACK_SCAN_LATERAL_MAX_UM)"),
        # anything but an http(s) URL was retried as an outage for a minute
        (["--estimator", "ftp://127.0.0.1:8100"], "must be an http:// or https:// URL"),
        (["--estimator", "notaurl"], "--estimator (FOCUSTRACK_SCAN_ESTIMATOR)"),
    ],
)
def test_a_refused_value_exits_2_naming_its_option(
    argv: list[str], needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        settings(*argv)
    assert exit_.value.code == 2
    assert needle in capsys.readouterr().err


def test_a_bad_name_or_policy_exits_2_before_any_connection(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert scan.run(settings("--instrument", "no/slash")) == 2
    assert scan.run(settings("--connect", "foo")) == 2  # an endpoint Zenoh cannot read
    assert capsys.readouterr().err.count("focustrack scan: error:") == 2


def test_the_demo_takes_the_scan_options_beside_its_own(monkeypatch: pytest.MonkeyPatch) -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, default=10)
    ScanOptions.add_arguments(parser)
    args = parser.parse_args(["--rows", "4", "--noise-sigma-um", "1.5", "--no-progress"])
    options = ScanOptions.from_args(args)
    assert options.noise_sigma_um == 1.5 and options.no_progress
    request = options.request("sim", "slide-0", "kf-rescan", {"prior_map_um": [0.0]})
    assert (request.noise_sigma_um, request.params) == (1.5, {"prior_map_um": [0.0]})
    monkeypatch.setenv("FOCUSTRACK_SCAN_FOCUS_ATTEMPTS", "9")
    assert ScanOptions.defaults().focus_attempts == 5  # code's scans read no environment
    assert ScanOptions.defaults(focus_attempts=2).request("a", "b", "c").focus_attempts == 2


def test_the_scan_command_loads_no_plotting_image_or_web_library() -> None:
    """`focustrack scan --help` and the scan's start load matplotlib, zarr, tifffile,
    FastAPI, uvicorn and tqdm only when they are used."""
    heavy = ("matplotlib", "zarr", "ome_zarr", "tifffile", "fastapi", "uvicorn", "tqdm")
    code = (
        "import sys, contextlib\n"
        "from focustrack_scheduler.scan import main\n"
        "with contextlib.suppress(SystemExit):\n"
        "    main(['--help'])\n"
        f"print(sorted(name for name in {heavy!r} if name in sys.modules))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.splitlines()[-1] == "[]"


def test_a_first_pass_makes_the_scan_a_realigned_second_pass(tmp_path: Path) -> None:
    assert settings().scan_request().realign is None
    (tmp_path / "mosaic.ome.zarr").mkdir()  # the first pass's output folder
    request = settings("--first-pass", str(tmp_path), "--lateral-tiles", "3").scan_request()
    assert request.realign == Realign(tmp_path, tiles=3, max_offset_um=10.0)


def _job(out: Path, *argv: str) -> scan.ScanJob:
    chosen = settings("--out", str(out), *argv)
    return scan.ScanJob(chosen.scan_request(), chosen.estimator, chosen.out)


def test_an_output_folder_of_a_run_that_never_made_its_slide_is_reused(tmp_path: Path) -> None:
    """A first run refused at its start (a strategy the estimator does not know) left its
    record without a slide: the corrected run takes the folder, where it was refused."""
    record = ScanRecord(tmp_path)
    try:
        record.state.save(estimator="http://127.0.0.1:8100", strategy="nope", slide="slide-0")
        assert scan._check_same_scan(record, _job(tmp_path)) is None
        record.state.save(slide_id="abc")  # a slide made: only the same scan resumes it
        with pytest.raises(ScanRefusedError, match="holds another scan"):
            scan._check_same_scan(record, _job(tmp_path))
    finally:
        record.close()


def test_a_scan_resumes_only_with_the_settings_its_slide_was_made_with(tmp_path: Path) -> None:
    """The estimator's slide keeps the settings it was made with: a run with other ones is
    refused by name (it used to go on with the old ones and write the new into scan.json);
    a folder from before the settings were kept resumes as it did."""
    made = _job(tmp_path, "--param", "q_um=0.2", "--max-frames", "21")
    record = ScanRecord(tmp_path)
    try:
        scan._record_scan(record, made)
        record.state.save(slide_id="abc")
        before = record.state.read()
        assert scan._check_same_scan(record, made) == "abc"
        slash = replace(made, estimator_url=made.estimator_url + "/")  # the same estimator
        assert scan._check_same_scan(record, slash) == "abc"
        assert (
            scan._check_same_scan(
                record, _job(tmp_path, "--max-frames", "21", "--param", "q_um=0.2")
            )
            == "abc"
        )
        for argv, named in [
            (("--param", "q_um=0.3", "--max-frames", "21"), "'params': {'q_um': 0.2}"),
            (("--param", "q_um=0.2"), "'max_frames': 21"),
            (
                ("--param", "q_um=0.2", "--max-frames", "21", "--start-z-um", "3"),
                "'start_z_um': 0.0",
            ),
        ]:
            with pytest.raises(ScanRefusedError, match="made with") as refused:
                scan._check_same_scan(record, _job(tmp_path, *argv))
            assert named in str(refused.value) and "resume it with them" in str(refused.value)
        assert record.state.read() == before  # nothing rewritten
        older = {
            name: before[name]
            for name in ("estimator", "instrument", "slide", "strategy", "slide_id")
        }
        record.state.path.write_text(json.dumps(older))
        assert scan._check_same_scan(record, _job(tmp_path, "--max-frames", "9")) == "abc"
    finally:
        record.close()


@pytest.mark.parametrize("flag", ["--live-port", "--metrics-port"])
def test_a_port_in_use_is_one_line(
    flag: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    alone = ["--mode", "peer", "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect"]
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = str(taken.getsockname()[1])
        assert scan.run(settings("--out", str(tmp_path / "out"), flag, port, *alone)) == 2
    err = capsys.readouterr().err
    assert f"cannot listen on 127.0.0.1:{port}" in err and "Traceback" not in err


def test_a_damaged_state_stops_the_scan_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / outputs.STATE_FILE).write_text("[1,2")
    alone = ["--mode", "peer", "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect"]
    assert scan.run(settings("--out", str(out), *alone)) == 1
    err = capsys.readouterr().err
    assert "scan.json is damaged: it is not JSON" in err and "Traceback" not in err


@pytest.mark.parametrize("out", ["a-file", "a-file/x"])
def test_an_output_folder_that_cannot_be_is_refused_before_the_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], out: str
) -> None:
    """Said at once: it used to wait for the Zenoh router first (30 s when none answers)."""
    (tmp_path / "a-file").write_text("mine")
    unanswered = f"tcp/127.0.0.1:{free_port()}"  # nothing listens: the bus would wait
    assert scan.run(settings("--out", str(tmp_path / out), "--connect", unanswered)) == 2
    err = capsys.readouterr().err
    why = f"{tmp_path / 'a-file'} is not a folder"
    assert f"--out {tmp_path / out} cannot be the output folder: {why}" in err
    assert "router" not in err and (tmp_path / "a-file").read_text() == "mine"


def test_the_wait_for_the_bus_is_the_scans_to_choose(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It was 30 s, whatever a script wanted: --bus-timeout-s ends it, in exit 1."""
    unanswered = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "out"
    argv = ("--out", str(out), "--connect", unanswered, "--bus-timeout-s", "2.5")
    assert scan.run(settings(*argv)) == 1
    err = capsys.readouterr().err
    assert f"no Zenoh router answers at {unanswered} yet; trying for 2.5 s" in err
    assert "focustrack scan: error:" in err and "Traceback" not in err


def test_a_first_pass_folder_without_a_mosaic_is_refused_before_the_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It was said once the slide's grid was known (exit 1, after 30 s without a router),
    a scan record left in --out."""
    unanswered = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "second"
    argv = ("--out", str(out), "--connect", unanswered, "--first-pass", str(tmp_path / "none"))
    with pytest.raises(SystemExit) as refused:  # argparse's exit 2, as for any bad flag
        scan.run(settings(*argv))
    assert refused.value.code == 2
    missing = tmp_path / "none" / "mosaic.ome.zarr"
    said = f"--first-pass (FOCUSTRACK_SCAN_FIRST_PASS): {missing} does not exist"
    assert said in capsys.readouterr().err
    assert not out.exists()


def test_a_state_file_of_another_tool_is_neither_merged_into_nor_resumed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    foreign = '{"slide_id": "x", "owner": "another tool"}'
    (out / outputs.STATE_FILE).write_text(foreign)
    alone = ["--mode", "peer", "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect"]
    assert scan.run(settings("--out", str(out), *alone)) == 1
    err = capsys.readouterr().err
    assert "scan.json is no scan's (it names no estimator" in err and "Traceback" not in err
    assert (out / outputs.STATE_FILE).read_text() == foreign


def test_a_damaged_partial_mosaic_stops_the_resumed_scan_before_a_stack_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    record = ScanRecord(out)
    try:
        scan._record_scan(record, _job(out))
        record.state.save(slide_id="abc")
    finally:
        record.close()
    (out / outputs.PARTIAL_MOSAIC).write_bytes(b"\x93NUMPY cut")
    alone = ["--mode", "peer", "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect"]
    assert scan.run(settings("--out", str(out), *alone)) == 1
    err = capsys.readouterr().err
    assert "mosaic.partial.npy is damaged" in err and "Traceback" not in err
    assert (
        not (out / outputs.LOG_FILE).exists()
        or "acquired" not in (out / outputs.LOG_FILE).read_text()
    )


def test_a_second_scan_into_a_folder_in_use_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two scans into one folder at once used to write one log, one mosaic and one state
    between them, and both ended "complete"."""
    out = tmp_path / "out"
    alone = ["--mode", "peer", "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect"]
    with scan._holding(out):  # as a running scan holds it
        assert scan.run(settings("--out", str(out), *alone)) == 1
    err = capsys.readouterr().err
    assert f"{out} is in use by another scan (process {os.getpid()})" in err
    assert "Traceback" not in err and not (out / outputs.STATE_FILE).exists()
    with scan._holding(out):  # released when the scan ends: the folder is free again
        pass


def test_no_phase_wins_over_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """A flag wins over the environment: `--no-phase` turns off FOCUSTRACK_SCAN_PHASE=1
    (there was no flag to do it)."""
    monkeypatch.setenv("FOCUSTRACK_SCAN_PHASE", "1")
    assert settings().phase and settings("--phase").phase
    assert not settings("--no-phase").phase


def test_phase_options_without_phase_are_named(monkeypatch: pytest.MonkeyPatch) -> None:
    """`--phase-planes 5` without `--phase` was taken in silence, and no phase came."""
    monkeypatch.setenv("FOCUSTRACK_SCAN_PHASE_TIMEOUT_S", "30")
    given = settings("--phase-planes", "5", "--phase-step-um", "0.3")
    assert given.ignored_phase_options() == [
        "--phase-planes",
        "--phase-step-um",
        "--phase-timeout-s",
    ]
    assert settings("--phase", "--phase-planes", "5").ignored_phase_options() == []
    monkeypatch.delenv("FOCUSTRACK_SCAN_PHASE_TIMEOUT_S")
    assert settings().ignored_phase_options() == []


def test_min_frames_above_max_frames_is_one_line_in_the_options_words(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """It was a pydantic dump of the estimator API's z-stack policy, once the options were
    taken; it is refused with them (exit 2)."""
    with pytest.raises(SystemExit) as refused:
        settings("--min-frames", "10", "--max-frames", "5")
    err = capsys.readouterr().err
    assert refused.value.code == 2 and "error: --min-frames 10 is above --max-frames 5" in err
    assert "pydantic" not in err
