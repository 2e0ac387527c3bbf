"""A prior map uploaded as an .npy file, positive prior sigmas, and the slide listing's pages:
against the real estimator (a uvicorn process on loopback, a real SQLite file), with the
client library; the 413s in process, where the client is not still sending when it comes.
"""

from __future__ import annotations

import asyncio
import io
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from subprocess import Popen

import httpx
import numpy as np
import pytest
from estimator_in_process import client, estimator, run

from focustrack_client import (
    AsyncEstimatorClient,
    ConflictError,
    EstimatorClient,
    InvalidRequestError,
    SlidePage,
)
from focustrack_client.models import (
    MAX_LISTED_VALUES,
    NEXT_CURSOR_HEADER,
    PRIOR_MAP_PARAM,
    PRIOR_SIGMA_PARAM,
    Grid,
    MeasurementIn,
    SlideCreate,
)
from focustrack_core.wire.session import free_port
from focustrack_estimator.event_store import Event, SequenceConflictError
from focustrack_estimator.prior import max_prior_bytes
from focustrack_estimator.service import spawn
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.sqlite_store import SQLiteStore

NPY = {"Content-Type": "application/octet-stream"}
SIDE = 200  # the slide: its map and sigmas are 1.6 MB of JSON


@contextmanager
def served(path: Path) -> Iterator[str]:
    """The estimator on a free port of loopback over the store at `path`: its URL."""
    port = free_port()
    process: Popen = spawn(path, port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        process.wait(timeout=10)


@pytest.fixture(scope="module")
def url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    with served(tmp_path_factory.mktemp("prior") / "estimator.sqlite") as base_url:
        yield base_url


def npy(array: np.ndarray) -> bytes:
    file = io.BytesIO()
    np.save(file, array)
    return file.getvalue()


def rescan(rows: int, cols: int, **params: object) -> SlideCreate:
    return SlideCreate(strategy="kf-rescan", grid=Grid(rows=rows, cols=cols), params=params)


def test_a_200x200_prior_map_is_uploaded_as_npy_and_scanned_with(url: str) -> None:
    rng = np.random.default_rng(3)
    map_um = rng.normal(0.0, 4.0, (SIDE, SIDE))
    sigma_um = rng.uniform(0.02, 0.2, (SIDE, SIDE))
    with EstimatorClient(url) as estimator:
        slide = estimator.create_slide(rescan(SIDE, SIDE, prior_map_sigma_um=[0.3]))
        estimator.put_prior(slide.id, npy(map_um.astype(np.float32)))  # the map alone
        params = estimator.slide(slide.id).config.params
        assert params[PRIOR_MAP_PARAM] == map_um.astype(np.float32).ravel().tolist()
        assert params[PRIOR_SIGMA_PARAM] == [0.3]  # a map alone keeps the sigma given
        estimator.put_prior(slide.id, npy(np.stack([map_um, sigma_um])))  # replaced whole
        params = estimator.slide(slide.id).config.params
        assert params[PRIOR_MAP_PARAM] == map_um.ravel().tolist()
        assert params[PRIOR_SIGMA_PARAM] == sigma_um.ravel().tolist()
        first = estimator.next(slide.id)
        # the first tile's prediction is the map's height there (no drift yet), and its
        # sigma the map's, the local change's and the start's together
        assert first.predicted_z_um == pytest.approx(map_um[0, 0])
        assert first.predicted_sigma_um == pytest.approx(
            np.sqrt(sigma_um[0, 0] ** 2 + 0.05**2 + 10.0**2)
        )
        assert first.sequence is not None and first.z_center_um is not None
        measurement = MeasurementIn(row=0, col=0, sequence=first.sequence, z_um=first.z_center_um)
        estimator.measure(slide.id, measurement)
        with pytest.raises(ConflictError) as late:  # the scan has begun on this prior
            estimator.put_prior(slide.id, npy(map_um))
        assert "before the first" in str(late.value.detail)


def test_a_negative_or_zero_prior_sigma_is_refused_naming_the_field(url: str) -> None:
    with EstimatorClient(url) as estimator:
        for sigma_um in (-0.1, 0.0):
            with pytest.raises(InvalidRequestError) as refused:
                estimator.create_slide(rescan(2, 2, prior_map_sigma_um=[0.1, sigma_um, 0.1, 0.1]))
            assert refused.value.status == 422
            (error,) = refused.value.detail
            assert error["loc"] == ["body", "params", PRIOR_SIGMA_PARAM]
            assert "greater than 0" in error["msg"] and repr(sigma_um) in error["msg"]


def _npy_header_only(shape: tuple[int, ...]) -> bytes:
    """An .npy file's header for float64 `shape`, and a few bytes of its data."""
    buffer = io.BytesIO()
    header = {"descr": "<f8", "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buffer, header)
    return buffer.getvalue() + bytes(160)


def test_a_prior_that_does_not_fit_the_slide_is_refused_saying_why(url: str) -> None:
    with EstimatorClient(url) as estimator:
        slide = estimator.create_slide(rescan(3, 4)).id
        other = estimator.create_slide(SlideCreate(strategy="kf-2d", grid=Grid(rows=3, cols=4))).id
    path = f"/v1/slides/{slide}/prior"
    good = np.zeros((3, 4))
    sigma_um = np.full((3, 4), 0.1)
    sigma_um[2, 1] = -0.1
    nan_um = good.copy()
    nan_um[1, 3] = np.nan
    refusals = {
        "shape (3, 4)": (npy(np.zeros((4, 3))), "(4, 3)"),
        "(2, 3, 4)": (npy(np.zeros((3, 3, 4))), "(3, 3, 4)"),
        "float64 or float32": (npy(good.astype(np.int64)), "int64"),
        "not an .npy file": (b'{"prior_map_um": []}', ""),
        # a header promising 4 TB: refused from the header, not a MemoryError (a 500)
        "must have shape (3, 4)": (_npy_header_only((100_000_000_000, 5)), "(100000000000, 5)"),
        "bytes beyond the (3, 4) array": (npy(good) + bytes(8), "8 bytes"),
        "sigma of the prior map must be finite and positive": (
            npy(np.stack([good, sigma_um])),
            "tile (2, 1) has -0.1",
        ),
        "height of the prior map must be finite": (npy(nan_um), "tile (1, 3) has nan"),
    }
    with httpx.Client(base_url=url) as http:
        for rule, (body, detail) in refusals.items():
            response = http.put(path, content=body, headers=NPY)
            assert response.status_code == 422, rule
            (error,) = response.json()["detail"]
            assert error["loc"] == ["body"] and rule in error["msg"] and detail in error["msg"]
        wrong_media = http.put(path, content=npy(good), headers={"Content-Type": "text/plain"})
        assert wrong_media.status_code == 415
        assert "application/octet-stream" in wrong_media.json()["detail"]
        with_charset = {"Content-Type": "Application/Octet-Stream; charset=binary"}
        assert http.put(path, content=npy(good), headers=with_charset).status_code == 204
        no_prior = http.put(f"/v1/slides/{other}/prior", content=npy(good), headers=NPY)
        assert no_prior.status_code == 422 and "takes no prior map" in no_prior.text
        nowhere = http.put("/v1/slides/nosuch/prior", content=npy(good), headers=NPY)
        assert nowhere.status_code == 404


def test_21_slides_are_listed_5_at_a_time_without_their_maps(tmp_path: Path) -> None:
    with served(tmp_path / "estimator.sqlite") as url:
        with EstimatorClient(url) as estimator:
            created = []
            for i in range(21):
                if i % 7 == 3:  # a few with a prior map (5 x 5: over MAX_LISTED_VALUES)
                    config = rescan(5, 5, prior_map_um=[float(i)] * 25, prior_map_sigma_um=[0.1])
                else:
                    config = SlideCreate(strategy="kf-wiener0", grid=Grid(rows=2, cols=2))
                created.append(estimator.create_slide(config).id)
            # the slide itself still has its map
            assert estimator.slide(created[3]).config.params[PRIOR_MAP_PARAM] == [3.0] * 25

        with httpx.Client(base_url=url) as http:
            # as a script follows the pages: a bare array each, the next one in the headers
            pages: list[list[str]] = []
            cursors: list[str] = []
            next_url: str | None = "/v1/slides?limit=5"
            while next_url is not None:
                response = http.get(next_url)
                assert response.status_code == 200
                listed = response.json()
                assert isinstance(listed, list)
                pages.append([slide["id"] for slide in listed])
                cursor = response.headers.get(NEXT_CURSOR_HEADER)
                if cursor is None:
                    assert "link" not in response.headers  # the last page: no next
                    next_url = None
                else:
                    next_url = f"/v1/slides?limit=5&cursor={cursor}"
                    assert response.headers["link"] == f'<{next_url}>; rel="next"'
                    assert response.links["next"]["url"] == next_url
                    cursors.append(cursor)
            assert [len(ids) for ids in pages] == [5, 5, 5, 5, 1]  # no empty last page
            # oldest first, none twice, none missed
            assert [slide_id for ids in pages for slide_id in ids] == created
            default = http.get("/v1/slides")  # one page of 100 at most: all 21, no next
            assert [slide["id"] for slide in default.json()] == created
            assert "link" not in default.headers and NEXT_CURSOR_HEADER not in default.headers
            for query in ({"limit": 0}, {"limit": 1001}, {"cursor": "not-a-cursor"}):
                refused = http.get("/v1/slides", params=query)
                assert refused.status_code == 422, query
                assert refused.json()["detail"][0]["loc"][0] == "query"

        with EstimatorClient(url) as estimator:
            page = estimator.list_slides_page(limit=5)
            client_pages, client_cursors = [[s.id for s in page.slides]], []
            while page.next_cursor is not None:
                client_cursors.append(page.next_cursor)
                page = estimator.list_slides_page(limit=5, cursor=page.next_cursor)
                client_pages.append([s.id for s in page.slides])
            assert (client_pages, client_cursors) == (pages, cursors)
            assert [s.id for s in estimator.iter_slides(page_size=5)] == created
            listed_slides = estimator.list_slides()  # every page, as before pages
            assert [s.id for s in listed_slides] == created
            for summary in listed_slides:
                params = summary.config.params
                assert all(
                    len(value) <= MAX_LISTED_VALUES
                    for value in params.values()
                    if isinstance(value, list)
                )
                with_map = summary.config.strategy == "kf-rescan"
                assert summary.omitted_params == ([PRIOR_MAP_PARAM] if with_map else [])
                assert params.get(PRIOR_SIGMA_PARAM) == ([0.1] if with_map else None)

        async def listed_async() -> tuple[SlidePage, list[str], list[str]]:
            async with AsyncEstimatorClient(url) as estimator:
                first = await estimator.list_slides_page(limit=5)
                walked = [s.id async for s in estimator.iter_slides(page_size=5)]
                return first, walked, [s.id for s in await estimator.list_slides()]

        first, walked, every = asyncio.run(listed_async())
        assert [s.id for s in first.slides] == pages[0] and first.next_cursor == cursors[0]
        assert walked == every == created


def test_a_prior_map_has_its_own_body_limit_and_every_other_route_keeps_its(
    tmp_path: Path,
) -> None:
    settings = EstimatorSettings()
    limit = max_prior_bytes(settings.max_grid_tiles)
    assert limit < 5 * 2**20  # the largest grid's map and sigmas, not any body at all

    async def exchange() -> tuple[int, int, int, int]:
        with estimator(tmp_path / "estimator.sqlite") as app:
            async with client(app) as http:
                body = rescan(SIDE, SIDE).model_dump(mode="json")
                body["params"] = {PRIOR_MAP_PARAM: [0.123456789] * SIDE**2}
                as_json = await http.post("/v1/slides", json=body)  # the 413 stays
                small = await http.post("/v1/slides", json=rescan(SIDE, SIDE).model_dump())
                slide_id = small.json()["id"]
                path = f"/v1/slides/{slide_id}/prior"
                stack = npy(np.stack([np.zeros((SIDE, SIDE)), np.full((SIDE, SIDE), 0.1)]))
                accepted = await http.put(path, content=stack, headers=NPY)
                too_large = await http.put(path, content=b"\0" * (limit + 1), headers=NPY)
                return as_json.status_code, accepted.status_code, too_large.status_code, len(stack)

    as_json, accepted, too_large, size = run(exchange())
    assert (as_json, accepted, too_large) == (413, 204, 413)
    assert settings.max_body_bytes < size < limit


def test_a_new_config_is_taken_only_before_the_first_event_and_drops_the_snapshot(
    tmp_path: Path,
) -> None:
    store = SQLiteStore(tmp_path / "estimator.sqlite")
    try:
        for slide_id in ("a", "b", "c"):
            store.create_slide(slide_id, {"v": 0})
        store.put_snapshot("a", 0, b"old state")
        store.replace_config("a", {"v": 1})
        record = store.slide("a")
        assert record is not None and record.config == {"v": 1}
        assert store.snapshot("a") is None  # a state of the configuration replaced
        store.append("b", Event(0, {}, {}, {}), accepted=True, done=False)
        with pytest.raises(SequenceConflictError):
            store.replace_config("b", {"v": 1})
        record = store.slide("b")
        assert record is not None and record.config == {"v": 0}
        first = store.slides_after(None, 2)
        assert [r.id for r in first] == ["a", "b"]
        after = (first[-1].created_s, first[-1].id)
        assert [r.id for r in store.slides_after(after, 2)] == ["c"]
    finally:
        store.close()
