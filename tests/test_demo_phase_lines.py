"""The demo's tables with and without phase stacks: the default one keeps its columns."""

from __future__ import annotations

from focustrack.demo import phase_line, wall_time_table
from focustrack_scheduler.outputs import WallTimes


def report(phase_s: float, tiles_with_phase: int, phase_images: int) -> dict:
    wall = WallTimes(rendering_s=2.0, estimation_s=1.0, phase_s=phase_s)
    wall.close(5.0)
    return {
        "wall_time_s": wall.as_dict(),
        "rows": 2,
        "cols": 3,
        "tiles_with_phase": tiles_with_phase,
        "phase_images_acquired": phase_images,
    }


def test_the_wall_time_table_shows_phase_only_for_scans_that_took_it() -> None:
    plain = wall_time_table({"kf-2d": report(0.0, 0, 0)})
    assert "phase" not in plain and plain.splitlines()[0].split()[-1] == "total"
    with_phase = wall_time_table({"kf-2d": report(1.5, 6, 66)})
    assert with_phase.splitlines()[0].split()[-3:] == ["phase", "scheduler", "total"]
    assert phase_line({"kf-2d": report(1.5, 5, 66), "af": report(1.0, 6, 66)}).startswith(
        "Phase: 11 of 12 tiles over 2 scans, 132 phase frames"
    )
