"""Wire schemas: generated code is current, field numbers never change, messages round-trip."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from focustrack_client import models as api
from focustrack_core.domain import FocusFlag
from focustrack_core.v1 import common_pb2, focus_pb2, instrument_pb2

#: Field numbers as released. Add new fields here; never change or reuse a number.
RELEASED_FIELDS = {
    common_pb2.Error: {"code": 1, "message": 2, "field": 3},
    instrument_pb2.AcquireRequest: {
        "slide": 1, "row": 2, "col": 3, "z_low_um": 4, "z_step_um": 5, "n_frames": 6,
        "sequence": 7, "exposure_s": 8, "nonce": 9,
    },
    instrument_pb2.Timing: {
        "move_s": 1, "z_settle_s": 2, "exposure_s": 3, "readout_s": 4, "total_s": 5,
        "clock_s": 6, "move_distance_um": 7,
    },
    instrument_pb2.ZStackHeader: {
        "instrument": 1, "slide": 2, "row": 3, "col": 4, "sequence": 5, "stage_x_um": 6,
        "stage_y_um": 7, "z_um": 8, "pixel_size_um": 9, "dtype": 10, "shape": 11,
        "channel_order": 12, "bit_depth": 13, "exposure_s": 14, "timestamp_unix_s": 15,
        "clock_s": 16, "nonce": 17, "tag": 18,
    },
    instrument_pb2.ZFrameHeader: {
        "stack": 1, "index": 2, "timestamp_unix_s": 3, "parts": 4, "part_offset": 5, "tag": 6,
    },
    instrument_pb2.ZStack: {"header": 1, "pixels": 2},
    instrument_pb2.AcquireReply: {"header": 1, "timing": 2},
    instrument_pb2.SlideTruth: {
        "instrument": 1, "slide": 2, "rows": 3, "cols": 4, "best_focus_um": 5, "drift_um": 6,
        "clock_s": 7,
    },
    focus_pb2.FocusResult: {
        "slide": 1, "row": 2, "col": 3, "sequence": 4, "metric": 5, "z_um": 6, "scores": 7,
        "best_z_um": 8, "sigma_um": 9, "compute_time_s": 11, "error": 12, "instrument": 13,
        "flags": 14,  # v0.2: the FocusFlag enum; number 10 (strings) is reserved
        "runner_up_z_um": 15, "chosen_probability": 16, "nonce": 17,
    },
}  # fmt: skip


ROOT = Path(__file__).resolve().parents[1]


def _generator():  # proto/generate.py is a script of the repository, not an installed module
    spec = importlib.util.spec_from_file_location("generate", ROOT / "proto" / "generate.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_generated_code_is_up_to_date(tmp_path: Path) -> None:
    generate = _generator()
    written = generate.generate(tmp_path)
    assert written, "no schema found under proto/"
    for path in written:
        checked_in = generate.PACKAGE_DIR / path.name
        assert checked_in.exists(), f"{checked_in} missing: run `make proto`"
        assert checked_in.read_bytes() == path.read_bytes(), f"{checked_in} is stale: `make proto`"


def test_focus_flags_are_one_vocabulary_in_proto_the_domain_and_the_client() -> None:
    proto = {
        name.removeprefix("FOCUS_FLAG_") for name in common_pb2.FocusFlag.DESCRIPTOR.values_by_name
    } - {"UNSPECIFIED"}
    assert {flag.name for flag in FocusFlag} == proto
    assert {(flag.name, flag.value) for flag in api.FocusFlag} == {
        (flag.name, flag.value) for flag in FocusFlag
    }
    for flag in FocusFlag:
        assert FocusFlag.of_proto(flag.proto) is flag
    assert FocusFlag.of_proto(99) is None  # a flag of a newer version is ignored


def test_released_field_numbers_are_kept() -> None:
    for message_type, fields in RELEASED_FIELDS.items():
        current = {f.name: f.number for f in message_type.DESCRIPTOR.fields}
        for name, number in fields.items():
            assert current.get(name) == number, f"{message_type.__name__}.{name} moved"
        numbers = list(current.values())
        assert len(numbers) == len(set(numbers))


def test_focus_result_round_trips_with_flags_and_absent_best_focus() -> None:
    result = focus_pb2.FocusResult(
        slide="s1", row=2, col=3, sequence=7, metric="normalized_variance",
        z_um=[0.0, 0.5, 1.0], scores=[1.0, 3.0, 2.0],
        flags=[FocusFlag.MULTI_PEAK.proto], compute_time_s=0.002,
    )  # fmt: skip
    decoded = focus_pb2.FocusResult.FromString(result.SerializeToString())
    assert not decoded.HasField("best_z_um") and not decoded.HasField("error")
    assert [FocusFlag.of_proto(flag) for flag in decoded.flags] == [FocusFlag.MULTI_PEAK]
    decoded.best_z_um = 0.6
    assert decoded.HasField("best_z_um") and decoded.best_z_um == 0.6
    assert list(decoded.scores) == [1.0, 3.0, 2.0]
