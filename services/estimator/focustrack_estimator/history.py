"""A slide's history: its logged acquisitions in order, read from the store when first needed."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import overload

from focustrack_estimator.records import Logged


class History(Sequence[Logged]):
    """A slide's logged acquisitions in order; those a snapshot covers are read on first use.

    After a restart the strategy comes from its snapshot, and only the events
    after it are needed (to replay): reading and decoding the events the
    snapshot covers took seconds for a 200x200 slide (40 000 events), so they
    are read from the store when something first asks for them (diagnostics,
    the re-post of an old measurement). `load` returns them.
    """

    def __init__(self, load: Callable[[], list[Logged]] | None = None, n_unread: int = 0) -> None:
        self._load, self._n_unread = load, n_unread
        self._items: list[Logged] = []

    def _read(self) -> None:
        if self._load is not None:
            self._items[:0] = self._load()
            self._load, self._n_unread = None, 0

    def __len__(self) -> int:
        return self._n_unread + len(self._items)

    @overload
    def __getitem__(self, index: int) -> Logged: ...

    @overload
    def __getitem__(self, index: slice) -> list[Logged]: ...

    def __getitem__(self, index: int | slice) -> Logged | list[Logged]:
        if isinstance(index, slice):
            self._read()
            return self._items[index]
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"history index {index} out of range")
        if index < self._n_unread:
            self._read()
        return self._items[index - self._n_unread]

    def __iter__(self) -> Iterator[Logged]:
        self._read()
        return iter(self._items)

    def append(self, logged: Logged) -> None:
        self._items.append(logged)
