"""Every numeric flag of `focustrack bench` is checked as argparse parses it: a bad value is
one line naming the flag and exit status 2, before any work, not a long run or a traceback.
"""

from __future__ import annotations

import argparse

import pytest

from focustrack.bench import chaos, instrument, rescan, transport
from focustrack.cli import main

HUGE = "99999999999999999999"


@pytest.mark.parametrize(
    ("sub", "flag", "value"),
    [
        ("chaos", "--duration-s", "nan"),
        ("chaos", "--duration-s", "-1"),
        ("chaos", "--down-max-s", "nan"),
        ("chaos", "--down-max-s", "-1"),
        ("chaos", "--gap-max-s", "nan"),
        ("chaos", "--gap-max-s", "-1"),
        ("chaos", "--replay-offset-um", "nan"),
        ("chaos", "--rows", "0"),
        ("chaos", "--cols", HUGE),
        ("chaos", "--size", "0"),
        ("chaos", "--faults", "-1"),
        ("chaos", "--scans", "0"),
        ("chaos", "--seed", "-1"),
        ("chaos", "--hostile-slides", HUGE),
        ("transport", "--fps", "nan"),
        ("transport", "--size", HUGE),
        ("transport", "--frames", "2"),
        ("transport", "--stacks", HUGE),
        ("instrument", "--repeats", "-1"),
        ("instrument", "--repeats", "0"),
        ("instrument", "--seed", "-1"),
        ("instrument", "--stacks", "-1"),
        ("instrument", "--stacks", "0"),
        ("instrument", "--stacks", HUGE),
        ("instrument", "--frames", "65"),
        ("instrument", "--size", HUGE),
        ("instrument", "--workers", "0"),
        ("instrument", "--workers", "257"),
        ("scale", "--jobs", "0"),
        ("scale", "--jobs", "65"),
        ("drift", "--lateral-tiles", HUGE),
        ("drift", "--check-textures", HUGE),
        ("focus", "--seed", HUGE),
        ("rescan", "--gap-s", "-1"),
        ("rescan", "--gap-s", "nan"),
        ("rescan", "--local-um", "-1"),
        ("rescan", "--local-um", "nan"),
        ("rescan", "--drift-um-per-s", "nan"),
        ("rescan", "--seed", "-1"),
        ("rescan", "--size", HUGE),
        ("rescan", "--maps", "0"),
        ("rescan", "--noise-um", "0"),
        ("rescan", "--dof-um", "inf"),
        ("drift", "--axial-offset-um", "nan"),
        ("drift", "--maps", HUGE),
        ("drift", "--seed", HUGE),
        ("phase", "--seed", "-1"),
        ("phase", "--size-px", HUGE),
        ("phase", "--size-px", "15"),
        ("phase", "--speed-size-px", HUGE),
        ("phase", "--repeats", HUGE),
        ("api", "--seed", "-1"),
        ("api", "--noise-um", "-1"),
        ("api", "--size", HUGE),
        ("slide", "--seeds", "-1"),
        ("slide", "--overlap", "nan"),
        ("mmcore", "--seed", "-1"),
        ("mmcore", "--exposure-ms", "nan"),
        ("mmcore", "--frames", "0"),
        ("startup", "--runs", HUGE),
        ("accuracy", "--maps", HUGE),
        ("accuracy", "--maps", "0"),
        ("accuracy", "--size", "1"),
        ("accuracy", "--noise-um", "0"),
        ("accuracy", "--dof-um", "nan"),
        ("accuracy", "--seed", "-1"),
        ("focus", "--reps", HUGE),
        ("focus", "--seed", "-1"),
        ("tune", "--maps-per-seed", "0"),
        ("tune", "--noise-um", "nan"),
        ("tune", "--seeds", HUGE),
        ("scale", "--sizes", HUGE),
        ("scale", "--unsnapshotted", "-1"),
    ],
)
def test_a_bad_value_is_one_argparse_error(
    capsys: pytest.CaptureFixture[str], sub: str, flag: str, value: str
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["bench", sub, flag, value])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1
    assert errors[0].startswith(f"focustrack bench {sub}: error: argument {flag}: ")


def test_a_huge_count_says_its_range(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["bench", "startup", "--runs", HUGE])
    assert f"argument --runs: must be in [1, 10000], got {HUGE}" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("module", "name", "default"),
    [
        (chaos, "replay_offset_um", 8.0),
        (transport, "fps", 100.0),
        (instrument, "frames", 21),
        (rescan, "seed", 1000),
    ],
)
def test_the_defaults_still_parse(module: object, name: str, default: float) -> None:
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)  # type: ignore[attr-defined]
    assert getattr(parser.parse_args([]), name) == default
