"""`focustrack demo`'s slide is checked against what the simulated instrument takes before
the stack starts: its refusal used to come as "instrument exited with status 2", with a
log to read, after the router and the services had started."""

from __future__ import annotations

import argparse

import pytest

from focustrack import demo


def demo_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    return parser.parse_args(list(argv))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--size", "63"], "--size must be even and at least 2, got 63"),
        (["--size", "100000"], "--size: Input should be less than or equal to 16384"),
        (["--rows", "2000"], "--rows: Input should be less than or equal to 1000"),
        (["--rows", "600", "--cols", "600"], "grid 600x600 is too large"),
        (["--overlap", "0.9", "--tissue-slide"], "--overlap: Input should be less than 0.5"),
        (["--cols", "0"], "--cols: Input should be greater than or equal to 1"),
    ],
)
def test_a_slide_the_instrument_would_refuse_is_named_in_the_demos_flags(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert demo.slide_problem(demo_args(*argv)) is not None
    assert demo.run(demo_args(*argv, "--no-rescan")) == 2
    assert f"focustrack demo: error: {message}" in capsys.readouterr().err


def test_the_default_slide_is_taken() -> None:
    assert demo.slide_problem(demo_args()) is None
    assert demo.slide_problem(demo_args("--tissue-slide", "--rows", "4", "--size", "256")) is None
