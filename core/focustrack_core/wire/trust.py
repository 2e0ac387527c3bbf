"""Keyed tags on the bus: focus results the scheduler can check, frames the focus service can.

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

from focustrack_core.v1 import instrument_pb2

#: The shortest key accepted, bytes (64 hex digits are 32 bytes of entropy).
MIN_KEY_BYTES = 32

#: Bytes of the nonce the scheduler (or the instrument, for a request without one) draws
#: for each acquisition.
NONCE_BYTES = 16
#: The longest nonce an instrument takes (it travels in every frame's header).
MAX_NONCE_BYTES = 64

#: The headers that carry a frame tag: a frame sample's, a stack sample's.
TaggedHeader = instrument_pb2.ZFrameHeader | instrument_pb2.ZStackHeader


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


class ResultSigner(_SharedKey):
    """Tags focus results and checks tags with one shared key."""

    kind = "result key"

    def tag(self, key_expr: str, payload: bytes) -> bytes:
        """The tag of a result published on `key_expr` (32 bytes)."""
        return self._mac(key_expr, payload)

    def verify(self, key_expr: str, payload: bytes, tag: bytes | None) -> bool:
        """True when `tag` is this key's tag of the result (in constant time)."""
        return tag is not None and hmac.compare_digest(self.tag(key_expr, payload), tag)


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
        if header.tag:
            raise ValueError("a header to tag has a tag already")
        unsigned = header.SerializeToString()
        tag = self._mac(key_expr, unsigned, hashlib.sha256(payload).digest())
        return unsigned + type(header)(tag=tag).SerializeToString()

    def verify(
        self, key_expr: str, header: TaggedHeader, attachment: bytes, payload: bytes
    ) -> bool:
        """True when the sample on `key_expr` whose `attachment` decoded to `header` carries
        this key's tag of it and of `payload` (compared in constant time)."""
        if not header.tag:
            return False
        tag_field = type(header)(tag=header.tag).SerializeToString()
        if not attachment.endswith(tag_field):
            return False  # the tag must come last, after the bytes it covers
        unsigned = attachment[: -len(tag_field)]
        expected = self._mac(key_expr, unsigned, hashlib.sha256(payload).digest())
        return hmac.compare_digest(expected, header.tag)


def frame_signer_of(path: Path | None) -> FrameSigner | None:
    """The signer of a ``--frame-key-file`` option (None: frames are not tagged or checked)."""
    return None if path is None else FrameSigner.from_file(path)
