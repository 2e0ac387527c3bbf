"""The demo's tables with and without phase stacks: the default one keeps its columns."""

from __future__ import annotations

from focustrack.demo import PhaseScores, phase_line, wall_time_table
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
    scores = PhaseScores([0.97, 0.93, 0.99], [0.004, -0.012, 0.003], 0)
    line = phase_line(report(1.5, 5, 66) | {"in_focus_fraction": 1.0}, scores)
    assert line.startswith("Phase pass (unstained red cells, 2x3 tiles, focus at the contrast")
    assert "6 of 6 tiles in focus, 5 with phase, 66 phase frames" in line
    assert line.endswith(
        "correlation with the true phase median 0.97, lowest 0.93; the glass at -0.01 rad at most"
    )
    none = phase_line(report(1.5, 0, 66) | {"in_focus_fraction": 0.5}, PhaseScores([], [], 0))
    assert none.endswith(
        "3 of 6 tiles in focus, 0 with phase, 66 phase frames, no phase to compare"
    )
    # a tile of bare glass has no cell to correlate with: left out, and said
    glass = PhaseScores([0.97, 0.99], [0.004, -0.002, 0.003], 1)
    assert phase_line(report(1.5, 3, 66) | {"in_focus_fraction": 1.0}, glass).endswith(
        "median 0.98, lowest 0.97 (1 of bare glass left out); the glass at +0.00 rad at most"
    )
