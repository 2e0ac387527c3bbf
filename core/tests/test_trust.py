"""The keyed tags of `focustrack_core.wire.trust`: frame tags that check only for the
instrument's key, the sample's key expression, header and bytes; keys read from files."""

from __future__ import annotations

from pathlib import Path

import pytest

from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire.trust import (
    MIN_KEY_BYTES,
    FrameSigner,
    ResultSigner,
    frame_signer_of,
    new_nonce,
    signer_of,
)

KEY_EXPR = "focustrack/v1/zframe/s1/2/3"
SIGNER = FrameSigner(b"k" * MIN_KEY_BYTES)


def _frame_header() -> instrument_pb2.ZFrameHeader:
    stack = instrument_pb2.ZStackHeader(
        slide="s1", row=2, col=3, sequence=5, nonce=b"n" * 16, z_um=[0.0, 0.5],
        dtype="<u2", shape=[2, 4, 4, 1],
    )  # fmt: skip
    return instrument_pb2.ZFrameHeader(stack=stack, index=1, parts=2, part_offset=16)


def _decoded(attachment: bytes) -> instrument_pb2.ZFrameHeader:
    return instrument_pb2.ZFrameHeader.FromString(attachment)


def test_a_frame_tag_checks_only_for_its_key_expression_header_payload_and_key() -> None:
    payload = bytes(range(16))
    attachment = SIGNER.attachment(KEY_EXPR, _frame_header(), payload)
    header = _decoded(attachment)
    assert len(header.tag) == 32 and header.part_offset == 16  # the header, then its tag
    assert SIGNER.verify(KEY_EXPR, header, attachment, payload)

    assert not SIGNER.verify(KEY_EXPR, header, attachment, payload[:-1] + b"\xff")
    assert not SIGNER.verify("focustrack/v1/zframe/s1/2/4", header, attachment, payload)
    assert not FrameSigner(b"x" * MIN_KEY_BYTES).verify(KEY_EXPR, header, attachment, payload)
    # the header cannot be changed under its tag: another part, another stack's nonce
    moved = _frame_header()
    moved.part_offset = 0
    forged = (
        moved.SerializeToString() + instrument_pb2.ZFrameHeader(tag=header.tag).SerializeToString()
    )
    assert not SIGNER.verify(KEY_EXPR, _decoded(forged), forged, payload)
    renonced = _frame_header()
    renonced.stack.nonce = b"o" * 16
    forged = (
        renonced.SerializeToString()
        + instrument_pb2.ZFrameHeader(tag=header.tag).SerializeToString()
    )
    assert not SIGNER.verify(KEY_EXPR, _decoded(forged), forged, payload)
    # an untagged header, or one with anything after its tag, does not check
    untagged = _frame_header().SerializeToString()
    assert not SIGNER.verify(KEY_EXPR, _decoded(untagged), untagged, payload)
    appended = attachment + instrument_pb2.ZFrameHeader(timestamp_unix_s=1.0).SerializeToString()
    assert not SIGNER.verify(KEY_EXPR, _decoded(appended), appended, payload)


def test_a_stack_header_is_tagged_alike_and_a_tagged_header_is_not_tagged_again() -> None:
    stack = _frame_header().stack
    attachment = SIGNER.attachment("focustrack/v1/zstack/s1/2/3", stack, b"pixels")
    decoded = instrument_pb2.ZStackHeader.FromString(attachment)
    assert SIGNER.verify("focustrack/v1/zstack/s1/2/3", decoded, attachment, b"pixels")
    with pytest.raises(ValueError, match="has a tag already"):
        SIGNER.attachment(KEY_EXPR, decoded, b"pixels")


def test_keys_come_from_files_and_a_short_or_missing_one_is_refused(tmp_path: Path) -> None:
    assert signer_of(None) is None and frame_signer_of(None) is None
    key_file = tmp_path / "frame.key"
    key_file.write_text("ab" * MIN_KEY_BYTES + "\n")
    signer = frame_signer_of(key_file)
    assert isinstance(signer, FrameSigner)
    payload = b"pixels"
    attachment = signer.attachment(KEY_EXPR, _frame_header(), payload)
    assert SIGNER.verify(KEY_EXPR, _decoded(attachment), attachment, payload) is False
    assert signer.verify(KEY_EXPR, _decoded(attachment), attachment, payload)
    assert isinstance(signer_of(key_file), ResultSigner)
    key_file.write_text("short\n")
    with pytest.raises(ValueError, match=r"frame key file .*frame.key: a frame key needs at least"):
        frame_signer_of(key_file)
    with pytest.raises(ValueError, match=r"result key file .*nowhere"):
        signer_of(tmp_path / "nowhere")


def test_nonces_are_fresh() -> None:
    assert len({new_nonce() for _ in range(100)}) == 100
