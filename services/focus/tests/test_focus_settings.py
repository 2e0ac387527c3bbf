"""The focus service's command: its options (flags, environment) -> its `FocusSettings` and
`FocusLimits`, and the modules it leaves until a stack needs them."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import pytest

from focustrack_core.wire.session import DEFAULT_ENDPOINT
from focustrack_focus.app import FocusLimits
from focustrack_focus.peak import PeakMode, PeakSettings
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.preprocess import Preprocess
from focustrack_focus.service import FocusServiceSettings, main


@pytest.fixture(autouse=True)
def no_focus_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """The options of each test are its own: none from the environment it runs in."""
    for name in os.environ:
        if name.startswith(FocusServiceSettings.env_prefix()):
            monkeypatch.delenv(name)


def parse(*argv: str) -> FocusServiceSettings:
    parser = argparse.ArgumentParser()
    FocusServiceSettings.add_arguments(parser)
    return FocusServiceSettings.from_args(parser.parse_args(list(argv)))


def test_the_defaults_are_the_focus_maths_own() -> None:
    """Lab software's `FocusSettings()` and the service without options read stacks alike."""
    settings = parse()
    assert settings.focus_settings() == FocusSettings()
    assert settings.limits() == FocusLimits()
    assert settings.stack_na == 0.85 and settings.endpoints() == ([DEFAULT_ENDPOINT], [])
    peak = settings.focus_settings().peak
    assert peak.min_relative_noise == 0.0 and peak.systematic_sigma_um == 0.0  # none learnt


def test_a_metric_calibrated_on_the_microscope_reaches_the_peak_settings() -> None:
    settings = parse(
        "--metric", "jpeg_size", "--focus-mode", "valley",
        "--min-relative-noise", "0.001", "--systematic-sigma-um", "0.15",
    ).focus_settings()  # fmt: skip
    assert settings.metric == "jpeg_size"
    assert settings.peak == PeakSettings(
        mode=PeakMode.VALLEY, min_relative_noise=0.001, systematic_sigma_um=0.15
    )


def test_the_environment_sets_the_limits_and_a_fixed_low_pass(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("FOCUSTRACK_FOCUS_MAX_FRAMES", "21")
    monkeypatch.setenv("FOCUSTRACK_FOCUS_BODY_TIMEOUT_S", "2.5")
    monkeypatch.setenv("FOCUSTRACK_FOCUS_LOWPASS_SIGMA_PX", "1.5")
    settings = parse("--min-structure-snr=-inf")
    assert settings.limits() == FocusLimits(max_frames=21, body_timeout_s=2.5)
    focus = settings.focus_settings()
    assert focus.preprocess == Preprocess(lowpass_sigma_px=1.5)
    assert focus.min_structure_snr == float("-inf")
    assert settings.stack_na is None  # a fixed low-pass is not matched to the optics


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--lowpass-sigma-px", "-1"], "focus service not started: low-pass sigma must be"),
    ],
)
def test_values_the_focus_maths_refuse_stop_the_command_with_status_2(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2  # before anything is served or opened
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--port", "70000"], "--port (FOCUSTRACK_FOCUS_PORT): Input should be less than"),
        (["--na", "0"], "--na (FOCUSTRACK_FOCUS_NA): Input should be greater than 0"),
        (["--na", "5"], "--na (FOCUSTRACK_FOCUS_NA): Input should be less than or equal to 1.7"),
        # "Input should be greater than or equal to -inf", which did not say NaN was wrong
        (["--min-structure-snr", "nan"], "SNR): a number of noise spreads, or -inf (never flat);"),
        (["--max-frames", "0"], "--max-frames (FOCUSTRACK_FOCUS_MAX_FRAMES): Input should be"),
        # a curve needs 3 points: 2 started a service that refused every curve and stack
        (["--max-frames", "2"], "MAX_FRAMES): Input should be greater than or equal to 3"),
        (["--max-upload-bytes", "1"], "--max-upload-bytes (FOCUSTRACK_FOCUS_MAX_UPLOAD_BYTES)"),
        (["--body-timeout-s", "0"], "--body-timeout-s (FOCUSTRACK_FOCUS_BODY_TIMEOUT_S): Input"),
        (["--lowpass-sigma-px", "1e9"], "--lowpass-sigma-px (FOCUSTRACK_FOCUS_LOWPASS_SIGMA_PX)"),
        (["--min-relative-noise", "2"], "--min-relative-noise (FOCUSTRACK_FOCUS_MIN_RELATIVE"),
        (["--systematic-sigma-um", "-0.1"], "--systematic-sigma-um (FOCUSTRACK_FOCUS_SYSTEMATIC"),
        # 1e308 started a service whose every curve was a 500 (sigma**2 overflowed)
        (
            ["--systematic-sigma-um", "1e308"],
            "SIGMA_UM): Input should be less than or equal to 1000",
        ),
        (["--metric", "nope"], "argument --metric: invalid choice: 'nope'"),
        (["--focus-mode", "min"], "argument --focus-mode: invalid choice: 'min'"),
        (["--slides", "scanner-1/*"], "--slides (FOCUSTRACK_FOCUS_SLIDES): slides"),
        (["--slides", "a$b"], "'a$b' is not a slide name or pattern"),
    ],
)
def test_values_the_options_refuse_are_usage_errors(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err


def test_the_command_starts_without_the_modules_only_stacks_need() -> None:
    """scipy (2 s to import) and tifffile wait for the first stack or curve that needs them,
    so /healthz answers sooner; the focus maths imports them where it uses them."""
    heavy = ("scipy", "tifffile", "matplotlib")
    probe = (
        "import sys, focustrack_focus.service; "
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & {set(heavy)!r}))"
    )
    started = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    assert started.stdout.strip() == "[]", started.stdout
