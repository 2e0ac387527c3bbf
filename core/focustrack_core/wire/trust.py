"""Trusted focus results: an HMAC over each result, with a key the focus service and the
scheduler share.

The router's access control (docs/security.md) lets only the focus service's user
publish on ``focustrack/v1/focus/**``, but that trusts every hop and every holder of
that password. The scheduler does not take a result on trust: the focus service puts
``HMAC-SHA256(key, key expression + NUL + payload)`` in the sample's attachment, and the
scheduler, given the same key, drops (and counts) every result whose tag is missing or
wrong. The key expression is in the tag, so a genuine result cannot be replayed onto
another slide's or tile's key; the payload names the stack (slide, tile, sequence,
frames), so it cannot be passed off as another stack's either.

The key is a file (``--result-key-file``, or the FOCUSTRACK_FOCUS_RESULT_KEY_FILE and
FOCUSTRACK_SCAN_RESULT_KEY_FILE variables) of at least `MIN_KEY_BYTES` bytes, e.g.
``python3 -c "import secrets; print(secrets.token_hex(32))" > result.key``.
"""

from __future__ import annotations

import hashlib
import hmac
from pathlib import Path

#: The shortest key accepted, bytes (64 hex digits are 32 bytes of entropy).
MIN_KEY_BYTES = 32


class ResultSigner:
    """Tags focus results and checks tags with one shared key."""

    def __init__(self, key: bytes) -> None:
        if len(key) < MIN_KEY_BYTES:
            raise ValueError(f"a result key needs at least {MIN_KEY_BYTES} bytes, got {len(key)}")
        self._key = key

    @classmethod
    def from_file(cls, path: str | Path) -> ResultSigner:
        """The key in file `path` (surrounding white space ignored); ValueError if unusable."""
        try:
            key = Path(path).read_bytes().strip()
        except OSError as error:
            raise ValueError(f"result key file {path}: {error.strerror}") from None
        try:
            return cls(key)
        except ValueError as error:
            raise ValueError(f"result key file {path}: {error}") from None

    def tag(self, key_expr: str, payload: bytes) -> bytes:
        """The tag of a result published on `key_expr` (32 bytes)."""
        return hmac.new(self._key, key_expr.encode() + b"\0" + payload, hashlib.sha256).digest()

    def verify(self, key_expr: str, payload: bytes, tag: bytes | None) -> bool:
        """True when `tag` is this key's tag of the result (in constant time)."""
        return tag is not None and hmac.compare_digest(self.tag(key_expr, payload), tag)


def signer_of(path: Path | None) -> ResultSigner | None:
    """The signer of a ``--result-key-file`` option (None: results are not tagged or checked)."""
    return None if path is None else ResultSigner.from_file(path)
