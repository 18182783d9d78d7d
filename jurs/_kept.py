"""Values made from an object and kept while the object lives, found by its identity.

jurs keeps several such values for immutable Modules: an adaptive spline's host
evaluator, a problem's parts, the flat split of a compiled call's argument. Modules that
hold arrays cannot be hashed, so a ``WeakKeyDictionary`` does not serve; the entry is
keyed by ``id`` and checked against a weak reference, which also drops it when the
object goes."""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any


class KeptByIdentity:
    """``get(obj, make)``: ``make(obj)``, made once while ``obj`` lives. An object that
    cannot be weakly referenced is not kept (its value is made on every call)."""

    def __init__(self) -> None:
        self._entries: dict[int, tuple[weakref.ref, Any]] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, obj, make: Callable[[Any], Any]):
        key = id(obj)
        entry = self._entries.get(key)
        if entry is not None and entry[0]() is obj:
            return entry[1]
        value = make(obj)
        try:
            ref = weakref.ref(obj, lambda _, key=key: self._entries.pop(key, None))
        except TypeError:  # not weakly referenceable: not kept
            return value
        self._entries[key] = (ref, value)
        return value
