"""The slide listing's pages: an opaque cursor that names the last slide of a page.

Slides are listed oldest first, by creation time and then id (`EventStore.slides_after`);
a cursor is that pair, as URL-safe base64 of its JSON, so that a client passes it back
as it got it and a slide created or deleted between two pages neither repeats nor
hides another.
"""

from __future__ import annotations

import base64
import binascii
import json
import math

from focustrack_estimator.errors import SlideError

#: Where a refused cursor is located, as a validation error's `loc` says it.
CURSOR_LOC = ("query", "cursor")


def encode_cursor(created_s: float, slide_id: str) -> str:
    """The cursor of a page that ends with the slide created at `created_s` (Unix s)."""
    text = json.dumps([created_s, slide_id], separators=(",", ":"))
    return base64.urlsafe_b64encode(text.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[float, str]:
    """The (created_s, id) a cursor names; a SlideError (422 at query.cursor) if it is not
    one this service gave."""
    try:
        padded = cursor + "=" * (-len(cursor) % 4)
        created_s, slide_id = json.loads(base64.urlsafe_b64decode(padded.encode()))
    except (binascii.Error, UnicodeDecodeError, ValueError, TypeError):
        created_s = slide_id = None
    if not (
        isinstance(created_s, float | int)
        and not isinstance(created_s, bool)
        and math.isfinite(created_s)
        and isinstance(slide_id, str)
    ):
        raise SlideError(
            "cursor is not one this service gave: pass the next_cursor of the previous page "
            "as it came, or none for the first page",
            CURSOR_LOC,
        )
    return float(created_s), slide_id
