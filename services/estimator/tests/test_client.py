"""The slim client against the real estimator: a uvicorn process on loopback, a real SQLite file.

Both clients, blocking and asyncio, drive a slide from creation to deletion and
read typed models back; every refusal arrives as the exception of its code.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from subprocess import Popen

import httpx
import numpy as np
import pytest
from tcp_relay import TcpRelay

from focustrack_client import (
    AsyncEstimatorClient,
    ConflictError,
    EstimatorClient,
    InvalidRequestError,
    SlideNotFoundError,
    UnauthorizedError,
)
from focustrack_client.models import Grid, MeasurementIn, SlideCreate
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn

TOKEN = "s3cret"


@pytest.fixture(scope="module")
def url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    port = free_port()
    process: Popen = spawn(tmp_path_factory.mktemp("client") / "estimator.sqlite", port, TOKEN)
    yield f"http://127.0.0.1:{port}"
    process.terminate()
    process.wait(timeout=10)


def test_the_blocking_client_scans_a_slide_and_deletes_it(url: str) -> None:
    with EstimatorClient(url, token=TOKEN) as estimator:
        slide = estimator.create_slide(
            SlideCreate(strategy="kf-wiener0", grid=Grid(rows=2, cols=3), label="client test")
        )
        assert slide.config.params["q"] == pytest.approx(0.14)  # every default resolved
        assert slide.id in {s.id for s in estimator.list_slides()}
        n_posted = 0
        while not (step := estimator.next(slide.id)).done:
            assert step.sequence is not None and step.z_center_um is not None
            measurement = MeasurementIn(
                row=step.row, col=step.col, sequence=step.sequence, z_um=step.z_center_um + 0.2
            )
            outcome = estimator.measure(slide.id, measurement)
            assert outcome.accepted and outcome.posterior_um is not None
            n_posted += 1
        assert n_posted == 6 and estimator.slide(slide.id).done
        focus_map = estimator.focus_map(slide.id)
        assert (focus_map.rows, focus_map.cols) == (2, 3)
        assert all(value is not None for row in focus_map.posterior_um for value in row)
        from_npy = focus_map_of_npy(estimator.focus_map_file(slide.id, "npy"))
        np.testing.assert_allclose(from_npy.posterior_um, np.array(focus_map.posterior_um))
        assert estimator.diagnostics(slide.id).n_accepted == 6
        with pytest.raises(ConflictError):  # the scan is complete: nothing is pending
            estimator.measure(slide.id, MeasurementIn(row=0, col=0, sequence=6, z_um=0.0))
        estimator.delete_slide(slide.id)
        with pytest.raises(SlideNotFoundError) as gone:
            estimator.slide(slide.id)
        assert gone.value.status == 404


def test_the_async_client_speaks_the_same_api(url: str) -> None:
    async def scan() -> tuple[int, int]:
        async with AsyncEstimatorClient(url, token=TOKEN) as estimator:
            slide = await estimator.create_slide(
                SlideCreate(strategy="kf-2d", grid=Grid(rows=2, cols=2))
            )
            steps = 0
            while not (step := await estimator.next(slide.id)).done:
                assert step.sequence is not None and step.z_center_um is not None
                body = MeasurementIn(
                    row=step.row, col=step.col, sequence=step.sequence, z_um=step.z_center_um
                )
                await estimator.measure(slide.id, body)
                steps += 1
            health = await estimator.health()
            await estimator.delete_slide(slide.id)
            served = await estimator.strategies()
            return steps, health.slides, {info.name for info in served}

    steps, n_slides, served = asyncio.run(scan())
    assert steps == 4 and n_slides >= 1 and {"kf-2d", "af-every-tile"} <= served


def test_the_client_lists_the_strategies_served_with_their_defaults(url: str) -> None:
    with EstimatorClient(url, token=TOKEN) as estimator:
        served = {info.name: info for info in estimator.strategies()}
        slide = estimator.create_slide(
            SlideCreate(strategy="kf-wiener0", grid=Grid(rows=1, cols=1))
        )
        estimator.delete_slide(slide.id)
    assert served["kf-wiener0"].defaults == slide.config.params  # what a slide is made with
    assert "q" in served["kf-wiener0"].parameters["properties"]


def test_refusals_are_typed_by_their_code(url: str) -> None:
    with EstimatorClient(url, token="wrong") as intruder, pytest.raises(UnauthorizedError):
        intruder.list_slides()
    with EstimatorClient(url, token=TOKEN) as estimator:
        with pytest.raises(InvalidRequestError) as refused:
            estimator.create_slide(SlideCreate(strategy="kf-nosuch", grid=Grid(rows=2, cols=2)))
        assert "unknown strategy" in str(refused.value.detail)
        slide = estimator.create_slide(SlideCreate(strategy="tile-skip", grid=Grid(rows=1, cols=2)))
        with pytest.raises(ConflictError):  # not the pending acquisition
            estimator.measure(slide.id, MeasurementIn(row=0, col=1, sequence=5, z_um=1.0))


def test_a_slide_id_is_one_path_segment_whatever_it_holds(url: str) -> None:
    """An id is quoted whole ("abc?x" deleted slide abc); one with a "/" is refused, as the
    service routes on the decoded path ("abc/map" read the map as a slide: a pydantic
    error, not the estimator's)."""
    with EstimatorClient(url, token=TOKEN) as estimator:
        slide = estimator.create_slide(SlideCreate(strategy="tile-skip", grid=Grid(rows=1, cols=2)))
        for other in (f"{slide.id}?x=1", f"{slide.id}#x", f"{slide.id} ", f"{slide.id}%2Fmap"):
            with pytest.raises(SlideNotFoundError):
                estimator.delete_slide(other)
            with pytest.raises(SlideNotFoundError):
                estimator.slide(other)
        for other in (f"{slide.id}/map", f"{slide.id}/..", ""):
            with pytest.raises(ValueError, match="one non-empty path segment"):
                estimator.delete_slide(other)
        assert estimator.slide(slide.id).id == slide.id  # still there


def test_a_lost_reply_is_asked_again_only_where_a_repeat_is_harmless(url: str) -> None:
    relay = TcpRelay(int(url.rpartition(":")[2]))
    try:
        with EstimatorClient(f"http://127.0.0.1:{relay.port}", token=TOKEN) as estimator:
            slide = estimator.create_slide(
                SlideCreate(strategy="kf-wiener0", grid=Grid(rows=2, cols=2))
            )
            step = estimator.next(slide.id)
            assert step.sequence == 0 and step.z_center_um is not None
            body = MeasurementIn(row=step.row, col=step.col, sequence=0, z_um=step.z_center_um)
            relay.drop_next_reply.set()
            outcome = estimator.measure(slide.id, body)  # recorded, reply lost, sent again
            assert not relay.drop_next_reply.is_set() and outcome.accepted
            assert estimator.next(slide.id).sequence == 1  # taken once
            n_slides = len(estimator.list_slides())
            relay.drop_next_reply.set()
            with pytest.raises(httpx.TransportError):  # not repeated: it would make two
                estimator.create_slide(
                    SlideCreate(strategy="kf-wiener0", grid=Grid(rows=2, cols=2))
                )
            assert len(estimator.list_slides()) == n_slides + 1
    finally:
        relay.close()


@pytest.mark.parametrize("client_type", [EstimatorClient, AsyncEstimatorClient])
def test_what_no_request_can_send_is_refused_when_the_client_is_made(client_type: type) -> None:
    """A URL without its scheme and a token with a control character inside were httpx's
    errors at the first request, after its retries; a token's line end is left out."""
    with pytest.raises(ValueError, match="must start with http:// or https://"):
        client_type("127.0.0.1:8100")
    with pytest.raises(ValueError, match="characters an HTTP header cannot carry"):
        client_type("http://127.0.0.1:8100", token="s3c\nret")
    client = client_type("http://127.0.0.1:8100", token="s3cret\n")  # as read from a file
    assert client.http.headers["Authorization"] == "Bearer s3cret"
