"""The scheduler creates a 200 x 200 kf-rescan slide at a real estimator (a uvicorn process,
an SQLite file): its prior map, 1.6 MB as JSON, goes as an .npy file after the creation."""

from __future__ import annotations

from pathlib import Path
from subprocess import Popen
from typing import Any, cast

import numpy as np

from focustrack_client import EstimatorClient
from focustrack_client import models as api
from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn
from focustrack_scheduler.engine import Engine
from focustrack_scheduler.plan import CreateOrResumeSlide, Plan
from focustrack_scheduler.record import ScanRecord

SIDE = 200


def test_the_scheduler_uploads_a_200x200_prior_map_as_npy(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    map_um = rng.normal(0.0, 3.0, (SIDE, SIDE))
    sigma_um = rng.uniform(0.03, 0.1, (SIDE, SIDE))
    params: dict[str, api.ParamValue] = {
        api.PRIOR_MAP_PARAM: map_um.ravel().tolist(),
        api.PRIOR_SIGMA_PARAM: sigma_um.ravel().tolist(),
    }
    config = api.SlideCreate(
        strategy="kf-rescan", grid=api.Grid(rows=SIDE, cols=SIDE), params=params
    )
    assert len(config.model_dump_json()) > 1_000_000  # what used to be refused: 413
    port = free_port()
    process: Popen = spawn(tmp_path / "estimator.sqlite", port)
    try:
        with EstimatorClient(f"http://127.0.0.1:{port}", timeout_s=30.0) as estimator:
            record = ScanRecord(tmp_path / "scan")
            # the instrument and the focus results play no part in creating a slide
            engine = Engine(cast(Any, None), cast(Any, None), estimator, record)
            slide_id = engine.run(_create(config))
            assert (record.state.read() or {})["slide_id"] == slide_id  # resumable, its prior in
            stored = estimator.slide(slide_id).config.params
            assert stored[api.PRIOR_MAP_PARAM] == params[api.PRIOR_MAP_PARAM]
            assert stored[api.PRIOR_SIGMA_PARAM] == params[api.PRIOR_SIGMA_PARAM]
            first = estimator.next(slide_id)
            assert first.predicted_z_um is not None
            assert abs(first.predicted_z_um - map_um[0, 0]) < 1e-9
    finally:
        process.terminate()
        process.wait(timeout=10)


def _create(config: api.SlideCreate) -> Plan:
    """A plan of one step: create the slide."""
    slide_id: str = yield CreateOrResumeSlide(config, None)
    return slide_id
