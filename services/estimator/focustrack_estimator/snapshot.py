"""Snapshots of a strategy's state: numpy arrays in an .npz blob plus a JSON tree, no pickle.

A restarted estimator rebuilds a slide from its newest snapshot and the events
logged after it, instead of replaying the whole log (docs/estimator-api.md).

What is stored is the strategy's attributes, walked recursively (`encode`):
numpy arrays go into the .npz archive (a list of same-shaped arrays, such as
a 1-D filter's history, as one stacked array, and a list of floats as one
float array), and everything else into a
JSON tree: numbers, strings, lists, tuples, dicts, sets, enums, dataclass
values (rebuilt from their fields), and objects of the estimator's own
classes (their attributes, recursively). Functions and other callables are
not stored: they come from the strategy's construction.

Restoring (`restore`) never creates an object from the file's say-so beyond
enums and dataclasses of the project's own packages (`_ALLOWED_MODULES`): the
strategy is first built from the slide's configuration, as for a replay, and
the snapshot's values are then written onto its objects, which must be of the
same classes at the same places. The archive is read with
``allow_pickle=False``. Anything unexpected raises `SnapshotError`, and the
caller falls back to replaying the whole log, which stays the source of truth.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import io
import json
from typing import Any

import numpy as np

#: Version of the encoding; a snapshot of another version is not restored (the log is).
# 2: FocusMap.out_of_focus_risk (was Strategy.risk); 3: the strategies' options are their
# pydantic parameter models (were FilterOptions dataclasses), the NSHP filters in nshp.py.
FORMAT = 3

#: Packages whose enums, dataclasses and objects a snapshot may name.
_ALLOWED_MODULES = ("focustrack_core.", "focustrack_estimator.", "filterpy.")

_TREE = "__tree__"


class SnapshotError(Exception):
    """A state that cannot be encoded, or a snapshot that does not fit the strategy."""


def _name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _allowed(cls: type) -> bool:
    return cls.__module__.startswith(_ALLOWED_MODULES)


def _class(name: str) -> type:
    module_name, _, qualname = name.partition(":")
    if not module_name.startswith(_ALLOWED_MODULES):
        raise SnapshotError(f"a snapshot may not name {name!r}")
    target: Any = importlib.import_module(module_name)
    for part in qualname.split("."):
        target = getattr(target, part)
    if not isinstance(target, type):
        raise SnapshotError(f"{name!r} is not a class")
    return target


class _Encoder:
    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def _array(self, array: np.ndarray) -> str:
        key = f"a{len(self.arrays)}"
        self.arrays[key] = array
        return key

    def node(self, value: Any, path: str) -> Any:
        if isinstance(value, enum.Enum):  # first: a StrEnum is a str, an IntEnum an int
            if not _allowed(type(value)):
                raise SnapshotError(f"{path}: enum {_name(type(value))} is not the project's")
            return {"e": _name(type(value)), "v": value.value}
        if value is None or isinstance(value, bool | str | int | float):
            return {"v": value}
        if isinstance(value, np.generic):
            return {"n": value.dtype.str, "v": value.item()}
        if isinstance(value, np.ndarray) and value.dtype == object:  # FilterPy's z: [[None]]
            return {"oa": self.node(value.tolist(), path), "shape": list(value.shape)}
        if isinstance(value, np.ndarray):
            return {"a": self._array(value)}
        if isinstance(value, list | tuple):
            kind = "l" if isinstance(value, list) else "t"
            if value and all(type(v) is float for v in value):  # a filter's innovations
                # One float64 array, not a JSON node per number: a 200x200 slide's 40 000
                # innovations took most of a restart's decoding.
                return {"fl": self._array(np.array(value, dtype=np.float64)), "k": kind}
            if value and all(isinstance(v, np.ndarray) for v in value):
                shapes = {(v.shape, v.dtype) for v in value}
                if len(shapes) == 1:
                    return {"s": self._array(np.stack(value)), "k": kind}
            return {kind: [self.node(v, f"{path}[{i}]") for i, v in enumerate(value)]}
        if isinstance(value, frozenset | set):
            kind = "fs" if isinstance(value, frozenset) else "set"
            return {kind: [self.node(v, f"{path}{{}}") for v in value]}
        if isinstance(value, dict):
            return {
                "d": [
                    [self.node(k, path), self.node(v, f"{path}[{k!r}]")] for k, v in value.items()
                ]
            }
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            cls = type(value)
            fields = dataclasses.fields(value)
            if not _allowed(cls) or not all(f.init for f in fields):
                raise SnapshotError(f"{path}: dataclass {_name(cls)} cannot be rebuilt")
            return {
                "dc": _name(cls),
                "v": {
                    f.name: self.node(getattr(value, f.name), f"{path}.{f.name}") for f in fields
                },
            }
        if callable(value):
            return {"keep": True}  # functions and bound methods come from the construction
        if hasattr(value, "__dict__") and _allowed(type(value)):
            return {"o": _name(type(value)), "v": self.attributes(value, path)}
        raise SnapshotError(f"{path}: cannot store a {type(value).__qualname__}")

    def attributes(self, obj: object, path: str) -> dict[str, Any]:
        return {name: self.node(value, f"{path}.{name}") for name, value in vars(obj).items()}


class _Decoder:
    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self.arrays = arrays

    def node(self, node: dict[str, Any], current: Any) -> Any:
        if "v" in node and len(node) == 1:
            return node["v"]
        if "e" in node:
            return _class(node["e"])(node["v"])
        if "n" in node:
            return np.dtype(node["n"]).type(node["v"])
        if "a" in node:
            return self.arrays[node["a"]]
        if "oa" in node:
            items = np.empty(int(np.prod(node["shape"])), dtype=object)
            items[:] = np.ravel(np.array(self.node(node["oa"], None), dtype=object))
            return items.reshape(node["shape"])
        if "s" in node:
            stacked = list(self.arrays[node["s"]])
            return stacked if node["k"] == "l" else tuple(stacked)
        if "fl" in node:
            floats = self.arrays[node["fl"]].tolist()  # Python floats, bit for bit
            return floats if node["k"] == "l" else tuple(floats)
        for kind, make in (("l", list), ("t", tuple)):
            if kind in node:
                previous = list(current) if isinstance(current, list | tuple) else []
                previous += [None] * (len(node[kind]) - len(previous))
                return make(self.node(n, old) for n, old in zip(node[kind], previous, strict=False))
        if "fs" in node:
            return frozenset(self.node(n, None) for n in node["fs"])
        if "set" in node:
            return {self.node(n, None) for n in node["set"]}
        if "d" in node:
            entries: dict[Any, Any] = current if isinstance(current, dict) else {}
            pairs = [(self.node(k, None), v) for k, v in node["d"]]
            return {k: self.node(v, entries.get(k)) for k, v in pairs}
        if "dc" in node:
            cls = _class(node["dc"])
            if not dataclasses.is_dataclass(cls):
                raise SnapshotError(f"{node['dc']!r} is not a dataclass")
            value = cls(**{name: self.node(n, None) for name, n in node["v"].items()})
            # An equal value of plain fields keeps the strategy's own object, with what it
            # has cached (a grid's serpentine order: 40 000 tiles to rebuild at 200x200).
            fields = (getattr(value, f.name) for f in dataclasses.fields(value))
            plain = all(isinstance(v, int | float | str | None) for v in fields)
            return current if plain and type(current) is cls and current == value else value
        if "keep" in node:
            if current is None:
                raise SnapshotError("a callable of the snapshot is missing from the strategy")
            return current
        if "o" in node:
            if current is None or _name(type(current)) != node["o"]:
                raise SnapshotError(
                    f"the snapshot holds a {node['o']} where the strategy has "
                    f"{type(current).__qualname__}"
                )
            self.attributes(current, node["v"])
            return current
        raise SnapshotError(f"unknown snapshot node {sorted(node)}")

    def attributes(self, obj: object, nodes: dict[str, Any]) -> None:
        current = vars(obj)
        for name, node in nodes.items():
            setattr(obj, name, self.node(node, current.get(name)))


def encode(strategy: object) -> bytes:
    """The strategy's state as an .npz archive (its arrays, and the JSON tree as bytes).

    Raises SnapshotError if some attribute cannot be stored.
    """
    encoder = _Encoder()
    tree = {"format": FORMAT, "class": _name(type(strategy))}
    tree["state"] = encoder.attributes(strategy, type(strategy).__name__)
    text = json.dumps(tree, separators=(",", ":"))
    buffer = io.BytesIO()
    arrays: dict[str, Any] = {**encoder.arrays, _TREE: np.frombuffer(text.encode(), np.uint8)}
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def restore(strategy: object, blob: bytes) -> None:
    """Write the state of `blob` (from `encode`) onto `strategy`, built from the same configuration.

    Raises SnapshotError when the snapshot is of another format or class, or does
    not fit the strategy's objects; the strategy is then half-written, to be discarded.
    """
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
        tree = json.loads(arrays.pop(_TREE).tobytes())
    except (ValueError, KeyError, OSError) as error:
        raise SnapshotError(f"unreadable snapshot: {error}") from None
    if tree.get("format") != FORMAT or tree.get("class") != _name(type(strategy)):
        raise SnapshotError(
            f"snapshot of format {tree.get('format')} for {tree.get('class')}, "
            f"not format {FORMAT} for {_name(type(strategy))}"
        )
    try:
        _Decoder(arrays).attributes(strategy, tree["state"])
    except (TypeError, ValueError, KeyError, AttributeError, ImportError) as error:
        raise SnapshotError(f"the snapshot does not fit the strategy: {error}") from None
