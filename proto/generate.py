"""Regenerate the Python code of the wire schemas: `make proto` (or `python proto/generate.py`).

Runs ``python -m grpc_tools.protoc -Iproto --python_out=OUT --pyi_out=OUT
proto/focustrack/v1/*.proto`` and moves the result from OUT/focustrack/v1 into the
core distribution's `focustrack_core/v1`, rewriting the generated imports
(`from focustrack.v1 import ...`) to that package. The schemas keep their proto
package `focustrack.v1`: it names the messages on the wire, in every language.
The test that the checked-in code is current runs this into a temporary folder.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

PROTO_DIR = Path(__file__).resolve().parent
#: Where the generated modules live: the core distribution's `focustrack_core.v1`.
PACKAGE_DIR = PROTO_DIR.parent / "core" / "focustrack_core" / "v1"


def proto_files() -> list[Path]:
    """Every schema, relative to proto/ (the include root), in a stable order."""
    return sorted(
        path.relative_to(PROTO_DIR) for path in (PROTO_DIR / "focustrack").rglob("*.proto")
    )


def generate(out_dir: Path = PACKAGE_DIR) -> list[Path]:
    """Write `*_pb2.py` and `*_pb2.pyi` for every schema into `out_dir`; return their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    with tempfile.TemporaryDirectory() as scratch:
        command = [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            f"-I{PROTO_DIR}",
            f"--python_out={scratch}",
            f"--pyi_out={scratch}",
            *(str(PROTO_DIR / name) for name in proto_files()),
        ]
        subprocess.run(command, check=True)
        for name in proto_files():
            for suffix in ("_pb2.py", "_pb2.pyi"):
                generated = Path(scratch) / name.parent / f"{name.stem}{suffix}"
                text = generated.read_text().replace(
                    "from focustrack.v1 import", "from focustrack_core.v1 import"
                )
                target = out_dir / generated.name
                target.write_text(text)
                written.append(target)
    return sorted(written)


def main() -> int:
    for path in generate():
        print(f"wrote {path.relative_to(PROTO_DIR.parent)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
