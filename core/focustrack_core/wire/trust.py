"""Keyed tags on the bus: results the scheduler can check, frames the services can.

The router's access control (docs/security.md) says who may publish where, but it trusts
every hop and every holder of a role's password. Two shared keys let the receivers check
for themselves, each with an HMAC-SHA256:

- **Results** (`ResultSigner`, ``--result-key-file`` of the focus service and the
  scheduler): the focus service puts ``HMAC(key, key expression + NUL + payload)`` in the
  result's attachment; the scheduler drops (and counts) every result whose tag is missing
  or wrong. The key expression is in the tag, so a genuine result cannot be replayed onto
  another tile's key; the payload names the stack (slide, tile, sequence, frames) and the
  acquisition's nonce, which the scheduler draws afresh for every acquisition, so an old
  genuine result is not one the scheduler is waiting for.
- **Frames** (`FrameSigner`, ``--frame-key-file`` of the instrument and the focus
  service): the instrument tags every frame and stack sample it publishes; the header it
  attaches is followed by its `tag` field, ``HMAC(key, key expression + NUL + the header's
  bytes before the tag + SHA-256 of the sample's payload)``. The focus service scores
  only samples whose tag checks, so frames published by anyone else never become a result.
  The tag covers the header's bytes as sent (no re-encoding on either side), and each
  sample alone: a frame in parts, a whole frame, a shared-memory payload alike.
- **Phase results** (`ResultSigner.attachment`, the phase service's ``--result-key-file``):
  a phase result's payload is its pixels and its `PhaseResult` header the attachment, so
  it is tagged as a frame is, with the result key: the attachment is the header (its
  `tag` empty), then its `tag` field, ``HMAC(key, key expression + NUL + the header's
  bytes before the tag + SHA-256 of the payload)``. The header names the tile, the
  stack's sequence and the acquisition's nonce, as a focus result does.

A key is a file of at least `MIN_KEY_BYTES` bytes (surrounding white space ignored), e.g.
``python3 -c "import secrets; print(secrets.token_hex(32))" > result.key``; the result
key and the frame key are different files (each shared by other services).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from pathlib import Path
from typing import Self

from focustrack_core.v1 import instrument_pb2, phase_pb2

#: The shortest key accepted, bytes (64 hex digits are 32 bytes of entropy).
MIN_KEY_BYTES = 32

#: Bytes of the nonce the scheduler (or the instrument, for a request without one) draws
#: for each acquisition.
NONCE_BYTES = 16
#: The longest nonce an instrument takes (it travels in every frame's header).
MAX_NONCE_BYTES = 64

#: The headers that carry a frame tag: a frame sample's, a stack sample's.
TaggedHeader = instrument_pb2.ZFrameHeader | instrument_pb2.ZStackHeader
#: The headers tagged with their payload: those, and a phase result's (with the result key).
Header = TaggedHeader | phase_pb2.PhaseResult


def new_nonce() -> bytes:
    """A fresh nonce for an acquisition: `NONCE_BYTES` random bytes (`secrets`)."""
    return secrets.token_bytes(NONCE_BYTES)


class _SharedKey:
    """A key shared by two services, read from a file: the HMACs of one kind of message."""

    #: What the key is for, in error messages.
    kind = "shared key"

    def __init__(self, key: bytes) -> None:
        if len(key) < MIN_KEY_BYTES:
            raise ValueError(f"a {self.kind} needs at least {MIN_KEY_BYTES} bytes, got {len(key)}")
        self._key = key

    @classmethod
    def from_file(cls, path: str | Path) -> Self:
        """The key in file `path` (surrounding white space ignored); ValueError if unusable."""
        try:
            key = Path(path).read_bytes().strip()
        except OSError as error:
            raise ValueError(f"{cls.kind} file {path}: {error.strerror}") from None
        try:
            return cls(key)
        except ValueError as error:
            raise ValueError(f"{cls.kind} file {path}: {error}") from None

    def _mac(self, key_expr: str, *parts: bytes) -> bytes:
        mac = hmac.new(self._key, key_expr.encode() + b"\0", hashlib.sha256)
        for part in parts:
            mac.update(part)
        return mac.digest()

    def _tagged(self, key_expr: str, header: Header, payload: bytes | bytearray) -> bytes:
        """`header` (whose `tag` is empty) followed by its `tag` field: this key's tag of
        the key expression, the header's bytes and the SHA-256 of `payload`."""
        if header.tag:
            raise ValueError("a header to tag has a tag already")
        unsigned = header.SerializeToString()
        tag = self._mac(key_expr, unsigned, hashlib.sha256(payload).digest())
        return unsigned + type(header)(tag=tag).SerializeToString()

    def _checks(
        self, key_expr: str, header: Header, attachment: bytes, payload: bytes | bytearray
    ) -> bool:
        """True when `attachment` (decoded to `header`) ends with this key's `_tagged` tag
        of the bytes before it and of `payload` (compared in constant time)."""
        tag = header.tag
        if not tag:
            return False
        tag_field = type(header)(tag=tag).SerializeToString()
        if not attachment.endswith(tag_field):
            return False  # the tag must come last, after the bytes it covers
        unsigned = attachment[: -len(tag_field)]
        expected = self._mac(key_expr, unsigned, hashlib.sha256(payload).digest())
        return hmac.compare_digest(expected, tag)


class ResultSigner(_SharedKey):
    """Tags results (focus and phase) and checks their tags with one shared key."""

    kind = "result key"

    def tag(self, key_expr: str, payload: bytes) -> bytes:
        """The tag of a result published on `key_expr` (32 bytes)."""
        return self._mac(key_expr, payload)

    def verify(self, key_expr: str, payload: bytes, tag: bytes | None) -> bool:
        """True when `tag` is this key's tag of the result (in constant time)."""
        return tag is not None and hmac.compare_digest(self.tag(key_expr, payload), tag)

    def attachment(self, key_expr: str, header: Header, payload: bytes | bytearray) -> bytes:
        """The attachment of a result whose header travels beside its payload (a phase
        result: a `PhaseResult` and its pixels) on `key_expr`: `header`, its `tag` empty,
        then the `tag` field (module docstring)."""
        return self._tagged(key_expr, header, payload)

    def verify_attachment(
        self, key_expr: str, header: Header, attachment: bytes, payload: bytes
    ) -> bool:
        """True when a result on `key_expr` whose `attachment` decoded to `header` carries
        this key's tag of it and of `payload` (`attachment`)."""
        return self._checks(key_expr, header, attachment, payload)


def signer_of(path: Path | None) -> ResultSigner | None:
    """The signer of a ``--result-key-file`` option (None: results are not tagged or checked)."""
    return None if path is None else ResultSigner.from_file(path)


class FrameSigner(_SharedKey):
    """The instrument's tags on its frame and stack samples, and their check.

    Each costs one SHA-256 of the payload (hashlib, which uses the CPU's SHA instructions
    where it has them; docs/security.md has the cost per MB) and an HMAC of the header.
    """

    kind = "frame key"

    def attachment(self, key_expr: str, header: TaggedHeader, payload: bytes | bytearray) -> bytes:
        """The attachment of a sample on `key_expr`: `header` (whose tag is empty), then
        its tag of that header and `payload` (the sample's bytes) as the `tag` field."""
        return self._tagged(key_expr, header, payload)

    def verify(
        self, key_expr: str, header: TaggedHeader, attachment: bytes, payload: bytes
    ) -> bool:
        """True when the sample on `key_expr` whose `attachment` decoded to `header` carries
        this key's tag of it and of `payload` (compared in constant time)."""
        return self._checks(key_expr, header, attachment, payload)


def frame_signer_of(path: Path | None) -> FrameSigner | None:
    """The signer of a ``--frame-key-file`` option (None: frames are not tagged or checked)."""
    return None if path is None else FrameSigner.from_file(path)
