"""Regenerate the Python code of the wire schemas: `python -m focustrack.wire.generate`.

Runs the documented command
``python -m grpc_tools.protoc -Iproto --python_out=. --pyi_out=. proto/focustrack/v1/*.proto``
from the repository root (or into another directory, which the up-to-date test uses).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

#: The repository root: proto/ and focustrack/ live here.
ROOT = Path(__file__).resolve().parents[2]
PROTO_DIR = ROOT / "proto"


def proto_files() -> list[Path]:
    """Every schema, relative to proto/ (the include root), in a stable order."""
    return sorted(
        path.relative_to(PROTO_DIR) for path in (PROTO_DIR / "focustrack").rglob("*.proto")
    )


def generate(out_dir: Path = ROOT) -> list[Path]:
    """Write `*_pb2.py` and `*_pb2.pyi` for every schema under `out_dir`; return their paths."""
    command = [
        sys.executable,
        "-m",
        "grpc_tools.protoc",
        f"-I{PROTO_DIR}",
        f"--python_out={out_dir}",
        f"--pyi_out={out_dir}",
        *(str(PROTO_DIR / name) for name in proto_files()),
    ]
    subprocess.run(command, check=True)
    return sorted(
        out_dir / name.with_name(f"{name.stem}_pb2{suffix}")
        for name in proto_files()
        for suffix in (".py", ".pyi")
    )


def main() -> int:
    for path in generate():
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
