"""A scan takes focus results only from the publisher it trusts.

The exploit: a spoofer that answered every stack with a wrong best z made a scan exit 0
with 7x the error. Here a rogue peer on the bus answers every stack, before the focus
service can, with the top of the stack plus 5 um (half untagged, half with a forged
tag). Without the shared key the scan takes the rogue's values (the control: the
exploit is real; here they even drive it out of the stage's travel); with it, not
one, the rejected results are counted in the report, and the scan's figures are those
of a clean scan.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from focustrack.bench.chaos import RoguePeer
from focustrack.local_stack import INSTRUMENT, SLIDE, LocalStack
from focustrack_scheduler import outputs
from focustrack_scheduler.engine import ScanRefusedError
from focustrack_scheduler.scan import ScanJob, run_scan
from focustrack_scheduler.settings import BEST_KALMAN, ScanOptions

pytestmark = pytest.mark.slow  # services in processes

ROWS = COLS = 4
SIZE = 192


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    instrument_args = [
        "--seed", "5", "--rows", str(ROWS), "--cols", str(COLS),
        "--width", str(SIZE), "--height", str(SIZE),
    ]  # fmt: skip
    with LocalStack(tmp_path_factory.mktemp("stack"), instrument_args) as running:
        yield running


def scan(stack: LocalStack, out_dir: Path, trusted: bool) -> dict:
    assert stack.session is not None
    job = ScanJob(
        request=ScanOptions.defaults().request(INSTRUMENT, SLIDE, BEST_KALMAN),
        estimator_url=stack.estimator_url,
        out_dir=out_dir,
        progress=False,
        trust=stack.trust if trusted else None,
    )
    return run_scan(stack.session, job)


def test_a_rogue_publisher_cannot_change_a_trusting_scan(stack: LocalStack, tmp_path: Path) -> None:
    clean = scan(stack, tmp_path / "clean", trusted=True)
    assert clean["focus_results_rejected"] == 0

    rogue = RoguePeer(stack.endpoint, SLIDE)
    try:
        with contextlib.suppress(ScanRefusedError):  # driven out of the stage's travel
            scan(stack, tmp_path / "fooled", trusted=False)
        wrong_when_fooled = rogue.wrong_accepted(tmp_path / "fooled" / outputs.LOG_FILE)
        guarded = scan(stack, tmp_path / "guarded", trusted=True)
        wrong_when_guarded = rogue.wrong_accepted(tmp_path / "guarded" / outputs.LOG_FILE)
    finally:
        rogue.close()

    assert wrong_when_fooled > 0  # the exploit: without the key, the rogue's z are taken
    assert wrong_when_guarded == 0
    assert guarded["focus_results_rejected"] >= guarded["acquisitions"]  # one per stack
    assert guarded["tiles_imaged"] == ROWS * COLS
    assert guarded["in_focus_fraction"] == pytest.approx(clean["in_focus_fraction"], abs=0.1)
    assert guarded["mae_um"] == pytest.approx(clean["mae_um"], abs=0.05)
