"""The live view's state (pure) and its server (real uvicorn on loopback, real HTTP)."""

from __future__ import annotations

import argparse
import io
import json
import threading
import time
from importlib.resources import files
from pathlib import Path

import httpx
import numpy as np
import pytest
from matplotlib.image import imread

from focustrack_core.domain import Acquisition, FocusFlag, Measurement, Outcome, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.in_focus import InFocusScore
from focustrack_scheduler.live import BY_FOCUS_SERVICE, BY_TRUTH, LiveScan
from focustrack_scheduler.live_view import LiveServer, port_number
from focustrack_scheduler.record import ScanRecord

GRID = ScanGrid(200, 200)  # the size the page must keep up with


def acquire_and_measure(record: ScanRecord, index: int, row: int, col: int, z_um: float) -> None:
    acquisition = Acquisition(index, row, col, ZRange(z_um - 1.0, 0.5, 5), Purpose.SCAN, True)
    record.acquired(acquisition, 5, 1.0)
    outcome = Outcome(row, col, True, posterior_um=z_um + 0.01, posterior_sigma_um=0.2)
    curve = ([z_um - 1.0, z_um - 0.5, z_um, z_um + 0.5, z_um + 1.0], [1.0, 2.0, 3.0, 2.0, 1.0])
    record.measurement(acquisition, Measurement(z_um, 0.3), outcome, curve)


def test_the_state_follows_the_record_and_streams_only_what_changed(tmp_path: Path) -> None:
    record = ScanRecord(tmp_path)
    acquire_and_measure(record, 0, 0, 0, 1.5)
    live = LiveScan.follow(record, GRID, "kf-2d")  # what was logged before is there
    first = live.changes()
    assert first["tiles"] == [[0, 0, 1.51, 0.2, 5, False, [], None]]
    acquire_and_measure(record, 1, 0, 1, 2.5)
    flat = Acquisition(2, 0, 2, ZRange(0.0, 0.5, 9), Purpose.SCAN, True)
    record.acquired(flat, 9, 1.0)
    flags = frozenset({FocusFlag.FLAT})
    record.measurement(flat, Measurement(None, flags=flags), Outcome(0, 2, False), None)
    update = live.changes(first["version"])
    assert [tile[:2] for tile in update["tiles"]] == [[0, 1], [0, 2]]  # only the new tiles
    assert update["tiles"][1] == [0, 2, None, None, 9, False, ["flat"], None]
    assert update["curve"]["row"] == 0 and update["curve"]["col"] == 1  # the latest curve
    assert update["curve"]["sigma_um"] == 0.3  # with the measurement's sigma, for its model
    assert update["images"] == 19 and update["tiles_total"] == 40_000
    assert live.changes(update["version"])["tiles"] == []  # nothing newer


def test_a_tiles_phase_shows_as_its_spread_in_radians(tmp_path: Path) -> None:
    record = ScanRecord(tmp_path)
    acquire_and_measure(record, 0, 0, 0, 1.5)
    live = LiveScan.follow(record, GRID, "kf-2d")
    field = np.zeros((2, 8, 8), np.float32)
    field[0, :, 4:] = 1.0  # half the tile a radian ahead: a spread of 0.5 rad
    grid = ScanGrid(2, 2)
    common = {"sequence": 1 << 40, "n_frames": 11, "scan_time_s": 0.3, "reference_z_um": 1.5}
    record.phase(grid, 0, 0, **common, field=field, background_share=0.4, error=None)
    record.phase(
        grid, 0, 1, **common, field=None, background_share=None,
        error="no phase result within 15 s",
    )  # fmt: skip
    tiles = {(t[0], t[1]): t for t in live.changes()["tiles"]}
    assert tiles[(0, 0)][7] == pytest.approx(0.5) and tiles[(0, 1)][7] is None
    again = LiveScan.follow(ScanRecord(tmp_path), GRID, "kf-2d")  # read back from the log
    assert again.changes()["tiles"][0][7] == pytest.approx(0.5)
    page = files("focustrack_scheduler").joinpath("live.html").read_text()
    assert 'id="phase"' in page and "rad" in page


def test_the_server_serves_the_page_the_state_and_server_sent_events(
    http: httpx.Client, tmp_path: Path
) -> None:
    record = ScanRecord(tmp_path)
    with LiveServer() as server:
        assert http.get(server.url + "live/state").status_code == 503  # no scan yet
        assert http.get(server.url + "healthz").json() == {"status": "ok", "scan": None}
        server.show(LiveScan.follow(record, GRID, "kf-2d"))
        assert http.get(server.url + "healthz").json() == {"status": "ok", "scan": "kf-2d"}
        acquire_and_measure(record, 0, 3, 4, 0.7)
        page = http.get(server.url)
        assert page.status_code == 200 and "EventSource" in page.text
        assert http.get(server.url + "live/state", params={"since": -1}).status_code == 422
        state = http.get(server.url + "live/state").json()
        assert state["tiles"] == [[3, 4, 0.71, 0.2, 5, False, [], None]]
        assert (state["pitch_um"], state["origin_x_um"]) == (GRID.pitch_um, GRID.origin_x_um)
        with http.stream("GET", server.url + "live/events", timeout=10) as events:
            lines = events.iter_lines()
            assert next(lines) == "event: update"
            data = json.loads(next(lines).removeprefix("data: "))
            assert data["since"] == 0 and data["tiles"] == state["tiles"]
            record.keep(GRID, 3, 4, 0.7, np.zeros((2, 2, 3)), 8)
            assert next(lines) == "" and next(lines) == "event: update"
            data = json.loads(next(lines).removeprefix("data: "))
            assert data["tiles"] == [[3, 4, 0.71, 0.2, 5, True, [], None]]
            assert data["tiles_done"] == 1


def follow_events(
    http: httpx.Client, url: str, events: list[tuple[str, str]], errors: list[Exception]
) -> None:
    """A browser's part: read `url`'s event stream to its end, as (event, data) pairs."""
    try:
        with http.stream("GET", url, timeout=30) as stream:
            name = ""
            for line in stream.iter_lines():
                if line.startswith("event: "):
                    name = line.removeprefix("event: ")
                elif line.startswith("data: "):
                    events.append((name, line.removeprefix("data: ")))
    except Exception as error:  # the test reports what the client saw
        errors.append(error)


def test_stopping_ends_every_stream_at_once_with_clients_connected(
    http: httpx.Client, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """The end of a scan with three browsers still following it: the server stops cleanly."""
    record = ScanRecord(tmp_path)
    server = LiveServer().start()
    server.show(LiveScan.follow(record, GRID, "kf-2d"))
    seen: list[list[tuple[str, str]]] = [[], [], []]
    errors: list[Exception] = []
    url = server.url + "live/events"
    clients = [
        threading.Thread(target=follow_events, args=(http, url, events, errors)) for events in seen
    ]
    for client in clients:
        client.start()
    deadline_s = time.monotonic() + 10.0
    while not all(seen) and time.monotonic() < deadline_s:  # each has its first update
        time.sleep(0.05)
    acquire_and_measure(record, 0, 1, 2, 0.7)
    started_s = time.monotonic()
    server.stop()  # what the scheduler does when the scan is over
    stop_s = time.monotonic() - started_s
    for client in clients:
        client.join(5.0)
    assert stop_s < 5.0  # a correctness bound: it used to wait 10 s, then 15 s more at exit
    assert not any(thread.name == "live-view" for thread in threading.enumerate())
    assert not any(client.is_alive() for client in clients) and errors == []
    for events in seen:  # each stream: updates, the scan's end, then the server's end
        assert [name for name, _ in events[:-1]] == ["update"] * (len(events) - 1)
        last = json.loads(events[-2][1])
        assert last["finished"] and events[-1] == ("end", "{}")
        tiles = [tile for _, data in events[:-1] for tile in json.loads(data)["tiles"]]
        assert [1, 2, 0.71, 0.2, 5, False, [], None] in tiles  # the change made while they followed
    logged = capfd.readouterr().err
    assert "Traceback" not in logged and "ERROR" not in logged, logged


@pytest.mark.parametrize("text", ["-1", "65536", "eighty"])
def test_a_bad_live_port_is_a_usage_error(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="a port is 0"):
        port_number(text)
    assert port_number("0") == 0 and port_number("8200") == 8200


def test_the_flag_legend_lists_every_flag() -> None:
    """Every flag the focus service can set has its colour (and so its legend entry)."""
    page = files("focustrack_scheduler").joinpath("live.html").read_text()
    legend = page.split("const FLAG_COLOURS = {", 1)[1].split("};", 1)[0]
    for flag in FocusFlag:
        assert f"{flag.value}:" in legend, flag


def test_kept_tiles_are_judged_in_focus_by_the_truth_or_else_by_the_focus_service(
    tmp_path: Path,
) -> None:
    record = ScanRecord(tmp_path)
    grid, frame = ScanGrid(3, 3), np.zeros((2, 2, 3))
    acquire_and_measure(record, 0, 0, 0, 1.5)
    record.keep(grid, 0, 0, 1.6, frame, 8)  # 0.1 um from the focus service's best z
    acquire_and_measure(record, 1, 0, 1, 2.5)
    record.keep(grid, 0, 1, 3.5, frame, 8)  # 1 um off
    for index, (col, flag) in enumerate([(2, FocusFlag.FLAT), (0, FocusFlag.EDGE_HIGH)], 2):
        row = 0 if flag is FocusFlag.FLAT else 1
        acquisition = Acquisition(index, row, col, ZRange(0.0, 0.5, 5), Purpose.SCAN, True)
        z_um = None if flag is FocusFlag.FLAT else 2.0
        measurement = Measurement(z_um, None if z_um is None else 0.3, frozenset({flag}))
        record.measurement(acquisition, measurement, Outcome(row, col, False), None)
        record.keep(grid, row, col, 2.0, frame, 8)  # no best z to judge it by
    record.keep_planes(grid, 1, 1, [0.0, 3.0], np.zeros((2, 2, 2, 3)), 8)
    record.keep(grid, 1, 1, 0.0, frame, 8)  # no measurement: not judged by the focus service
    assert LiveScan.follow(record, grid).changes()["in_focus"] is None  # no depth of field
    by_focus = LiveScan.follow(record, grid, dof_um=1.0).changes()["in_focus"]
    assert by_focus == {"tiles": 1, "judged": 2, "by": BY_FOCUS_SERVICE, "tissue_only": False}
    truth_um = np.array([[0.0, 3.4, 2.2], [0.0, 3.1, 9.0], [0.0, 0.0, 0.0]])
    live = LiveScan.follow(record, grid, dof_um=1.0, truth_um=truth_um)
    # by the truth every kept tile is judged, (1, 1) on its planes: the progress bar's figure
    by_truth = {"by": BY_TRUTH, "tissue_only": False}
    assert live.changes()["in_focus"] == {"tiles": 3, "judged": 5} | by_truth
    assert InFocusScore(truth_um, 1.0).tiles(record.tally.kept, record.tally.planes) == 3
    record.keep(grid, 1, 2, 9.2, frame, 8)  # while it follows: one more, in focus
    assert live.changes()["in_focus"] == {"tiles": 4, "judged": 6} | by_truth
    glass = np.zeros(grid.shape, bool)
    glass[0, 0] = glass[0, 1] = True  # the truth's empty glass: not judged, in focus or not
    tissue = LiveScan.follow(record, grid, dof_um=1.0, truth_um=truth_um, empty_glass=glass)
    assert tissue.changes()["in_focus"] == {"tiles": 3, "judged": 4} | by_truth | {
        "tissue_only": True
    }


def test_the_server_serves_thumbnails_of_the_tiles_kept(http: httpx.Client, tmp_path: Path) -> None:
    """Each tile's image shows in its cell of the PNG as it is kept, and again after a
    restart (read from the partial mosaic on disk)."""
    grid = ScanGrid(3, 3, pitch_um=16.0)  # tiles of 16 px of 1 um, side by side
    record = ScanRecord(tmp_path)
    record.state.save(tile={"height": 16, "width": 16, "channels": 3, "pixel_size_um": 1.0})
    with LiveServer() as server:
        assert http.get(server.url + "live/thumbnails.png").status_code == 503  # no scan yet
        server.show(LiveScan.follow(record, grid, "kf-2d"))
        before = http.get(server.url + "live/state").json()["thumbnails_version"]
        record.keep(grid, 1, 2, 0.5, np.full((16, 16, 3), 4095, np.uint16), 12)
        state = http.get(server.url + "live/state").json()
        assert state["thumbnails_version"] == before + 1
        response = http.get(server.url + "live/thumbnails.png")
        assert response.headers["content-type"] == "image/png"
        thumbnails = imread(io.BytesIO(response.content))
        cell = thumbnails.shape[0] // grid.rows
        assert thumbnails.shape == (3 * cell, 3 * cell, 4)
        assert (thumbnails[cell : 2 * cell, 2 * cell :] == 1.0).all()  # white, opaque
        assert (thumbnails[:cell, ..., 3] == 0).all()  # not kept: transparent
    record.close()
    again = LiveScan.follow(ScanRecord(tmp_path), grid)  # a restarted scheduler's view
    assert (again.thumbnails.rgba[cell : 2 * cell, 2 * cell :] == 255).all()


def test_every_map_layer_has_a_colour_scale_of_its_own_with_its_unit() -> None:
    """Each numeric layer: its own bar, low and high ends and unit; the flags: a legend."""
    page = files("focustrack_scheduler").joinpath("live.html").read_text()
    units = {"z": "um", "sigma": "um", "images": "images", "phase": "rad"}
    for layer, unit in units.items():
        panel = page.split(f'id="{layer}"></canvas>', 1)[1].split("</div></div>", 1)[0]
        assert f'id="{layer}-bar"' in panel and f'id="{layer}-low"' in panel, layer
        assert f"<span>{unit}</span>" in panel, layer
    assert 'id="flag-legend"' in page and 'id="thumbs"' in page
    assert "live/thumbnails.png" in page and "ticks(zl, zh" in page  # the curve's z ticks
