"""Safe network defaults of a deployment: compose takes the tokens from a .env file
(.env.example documents them). Each service's own: its tests folder; the refusal helper's:
core/tests/test_serving.py."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_compose_takes_every_token_from_the_env_file() -> None:
    compose = (ROOT / "compose.yaml").read_text()
    example = (ROOT / ".env.example").read_text()
    tokens = set(re.findall(r"\$\{(FOCUSTRACK_\w+_TOKEN)", compose))
    assert tokens == {
        "FOCUSTRACK_ESTIMATOR_TOKEN",
        "FOCUSTRACK_FOCUS_TOKEN",
        "FOCUSTRACK_PHASE_TOKEN",
    }
    for token in tokens:
        assert re.search(rf"^{token}=\S+", example, re.MULTILINE), token
    assert ".env" in (ROOT / ".gitignore").read_text().split()  # secrets stay out of git
