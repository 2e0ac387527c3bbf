"""Write each service's requirements.txt from uv.lock: the pinned third-party packages it needs.

Its image installs exactly these (`pip install --no-deps -r requirements.txt` and the
workspace's own distributions), so an image rebuilt later gets the same numerics.
`make lock` runs this after `uv lock`; a test checks the files are current.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SERVICES = ("estimator", "focus", "instrument_sim", "phase", "scheduler")
#: The extras a service's image installs: the focus and phase distributions' bases are their
#: maths alone.
EXTRAS = {"focus": ("service",), "phase": ("service",)}


def export(service: str) -> str:
    """The requirements of `service` as `uv export` writes them from the lock file."""
    package = "focustrack-" + service.replace("_", "-")
    command = [
        "uv", "export", "--package", package, "--frozen", "--no-dev", "--no-hashes",
        "--no-emit-workspace", "--no-annotate", "--no-header", "--quiet",
        *(f"--extra={extra}" for extra in EXTRAS.get(service, ())),
    ]  # fmt: skip
    uv = Path(sys.executable).with_name("uv")
    command[0] = str(uv) if uv.exists() else "uv"
    return subprocess.run(command, cwd=ROOT, check=True, capture_output=True, text=True).stdout


def main() -> int:
    for service in SERVICES:
        path = ROOT / "services" / service / "requirements.txt"
        path.write_text(export(service))
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
