"""Each distribution installs alone, as its image installs it, in a plain virtualenv.

The install step of every service's Dockerfile runs here as written (its /src paths
pointed at this checkout): exactly the lock file's versions, then the workspace's own
distributions, and `pip check` must pass. The estimator pulls neither OpenCV nor
Zenoh; the client pulls httpx and pydantic and what they need, nothing more. The lab's
documented install line runs its documented example (docs/integrations/pymmcore-plus.md)
without the services' Zenoh, FastAPI, uvicorn or OpenCV.
Slow (a virtualenv and an install each): CI runs them, `make test-fast` skips them.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

#: service folder -> its console script
SERVICES = {
    "estimator": "focustrack-estimator",
    "focus": "focustrack-focus",
    "instrument_sim": "focustrack-instrument-sim",
    "phase": "focustrack-phase",
    "scheduler": "focustrack-scheduler",
}
#: What the client may bring: httpx, pydantic, the OpenTelemetry API (pure Python: the
#: caller's trace context goes with each request; a no-op without an SDK), and their own
#: dependencies.
CLIENT_CLOSURE = {
    "focustrack-client", "httpx", "httpcore", "h11", "anyio", "idna", "certifi", "sniffio",
    "pydantic", "pydantic-core", "annotated-types", "typing-extensions", "typing-inspection",
    "opentelemetry-api", "pip", "setuptools",
}  # fmt: skip


#: What a lab's acquisition environment must not get: the services' network and image stack.
SERVICE_ONLY = ("eclipse-zenoh", "fastapi", "uvicorn", "opencv-python-headless", "tifffile")
#: The page whose install line and example the lab's install test runs.
LAB_DOC = ROOT / "docs" / "integrations" / "pymmcore-plus.md"

#: uv runs pip's install step with pip's semantics, ten times faster (it is in the dev tools).
UV = str(Path(sys.executable).with_name("uv"))


def venv(path: Path) -> Path:
    """A new, empty virtualenv at `path`; its python."""
    subprocess.run([UV, "venv", "--quiet", "--python", sys.executable, str(path)], check=True)
    return path / "bin" / "python"


def pip(python: Path, *args: str) -> str:
    """`pip ARGS` in the virtualenv of `python` (run by uv); its output."""
    command = [UV, "pip", args[0], "--python", str(python), *args[1:]]
    return subprocess.run(command, check=True, capture_output=True, text=True).stdout


def installed(python: Path) -> set[str]:
    listing = json.loads(pip(python, "list", "--format=json"))
    return {entry["name"].lower().replace("_", "-") for entry in listing}


def dockerfile_install(folder: str, src: Path) -> list[str]:
    """The `pip install ...` arguments of the service's Dockerfile (its install steps, the
    locked requirements' and the distributions', in one), its /src copied to `src`.

    As the image's COPY lines do, the distributions are copied first, so building
    them leaves nothing in this checkout.
    """
    dockerfile = (ROOT / "services" / folder / "Dockerfile").read_text()
    ignore = shutil.ignore_patterns("build", "*.egg-info", "__pycache__", "tests")
    for copied in re.findall(r"^COPY (\S+) /src/\S+$", dockerfile, flags=re.MULTILINE):
        if (ROOT / copied).is_dir():  # a file copied alone (requirements.txt) is in its folder
            shutil.copytree(ROOT / copied, src / copied, ignore=ignore, dirs_exist_ok=True)
    steps = re.findall(r"pip install ([^&\n]+)", dockerfile.replace("\\\n", " "))
    assert steps, f"services/{folder}/Dockerfile has no pip install step"
    words = dict.fromkeys(word for step in steps for word in step.split())  # --no-deps once
    return [word.replace("/src/", f"{src}/") for word in words]


@pytest.mark.parametrize("folder", sorted(SERVICES))
def test_each_dockerfiles_install_step_works_in_a_plain_venv(tmp_path: Path, folder: str) -> None:
    script = SERVICES[folder]
    python = venv(tmp_path / "venv")
    pip(python, "install", "--quiet", *dockerfile_install(folder, tmp_path / "src"))
    pip(python, "check")
    help_text = subprocess.run(
        [python.with_name(script), "--help"], check=True, capture_output=True, text=True
    ).stdout
    # the console script starts: every import resolves (argparse wraps lines anywhere)
    assert "[env FOCUSTRACK_" in " ".join(help_text.split())
    packages = installed(python)
    assert "focustrack" not in packages  # the umbrella is not needed to run a service
    if folder == "estimator":
        assert not {p for p in packages if "opencv" in p or "zenoh" in p}, packages
        # Its strategies load after it starts, so `--help` does not import them: this does.
        subprocess.run([python, "-c", "import focustrack_estimator.slide"], check=True)


def test_the_client_installs_with_httpx_pydantic_and_the_opentelemetry_api_only(
    tmp_path: Path,
) -> None:
    python = venv(tmp_path / "venv")
    shutil.copytree(ROOT / "client", tmp_path / "client", ignore=shutil.ignore_patterns("build"))
    pip(python, "install", "--quiet", str(tmp_path / "client"))
    extra = installed(python) - CLIENT_CLOSURE
    assert not extra, f"the client pulled {sorted(extra)}"
    subprocess.run([python, "-c", "from focustrack_client import AsyncEstimatorClient"], check=True)


def documented_lab_install(doc: str) -> list[str]:
    """The arguments of the page's `pip install` line (its one sh line that has one)."""
    lines = re.findall(r"^pip install (.+)$", doc, flags=re.MULTILINE)
    assert len(lines) == 1, f"{LAB_DOC.name} should have one pip install line, has {lines}"
    return [word.strip("'") for word in lines[0].split()]


def documented_example(doc: str) -> str:
    """The page's example program: its python block that starts `# example_mmcore.py`."""
    blocks = re.findall(r"```python\n(# example_mmcore\.py\n.*?)```", doc, flags=re.DOTALL)
    assert len(blocks) == 1, f"{LAB_DOC.name} should have one example_mmcore.py block"
    return blocks[0]


def test_the_documented_lab_install_runs_the_documented_example(tmp_path: Path) -> None:
    doc = LAB_DOC.read_text()
    ignore = shutil.ignore_patterns("build", "*.egg-info", "__pycache__", "tests")
    paths = documented_lab_install(doc)
    for path in paths:  # copied first, so building them leaves nothing in this checkout
        folder = path.split("[")[0]
        shutil.copytree(ROOT / folder, tmp_path / folder, ignore=ignore)
    # The lock's versions (the ones CI tests), as constraints: the line itself is unchanged.
    lock = subprocess.run(
        [UV, "export", "--frozen", "--package", "focustrack-lab", "--extra", "mmcore",
         "--no-dev", "--no-hashes", "--no-emit-workspace", "--no-annotate", "--no-header",
         "--quiet"],
        cwd=ROOT, check=True, capture_output=True, text=True,
    ).stdout  # fmt: skip
    (tmp_path / "constraints.txt").write_text(lock)
    python = venv(tmp_path / "venv")
    install = ["install", "--quiet", "-c", str(tmp_path / "constraints.txt")]
    subprocess.run([UV, "pip", *install, "--python", str(python), *paths], cwd=tmp_path, check=True)
    packages = installed(python)
    assert not packages & set(SERVICE_ONLY), sorted(packages & set(SERVICE_ONLY))
    assert "focustrack" not in packages and "focustrack-lab" in packages
    # the focus service's command is there, and says which extra it needs
    refused = subprocess.run(
        [python.parent / "focustrack-focus", "--help"], capture_output=True, text=True
    )
    assert refused.returncode == 2
    assert "pip install 'focustrack-focus[service]'" in refused.stderr, refused.stderr

    (tmp_path / "example_mmcore.py").write_text(documented_example(doc))
    port = free_port()
    estimator = spawn(tmp_path / "estimator.sqlite", port, timeout_s=120)
    try:
        run = subprocess.run(
            [python, "example_mmcore.py"],
            cwd=tmp_path,
            env={**os.environ, "FOCUSTRACK_ESTIMATOR_URL": f"http://127.0.0.1:{port}"},
            check=True,
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        estimator.terminate()
        estimator.wait(timeout=10)
    assert "on 36 tiles; no tile without a focus" in run.stdout, run.stdout
    error_um = float(re.findall(r"largest focus error (\S+) um", run.stdout)[0])
    assert error_um <= 0.5  # half the demo's depth of field (1 um)
