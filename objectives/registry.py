"""The one kind of registry: named entries of one kind (weightings, policy heads, simulator suites, importers).

Every choice a user makes by name (``objective=tar``, ``policy=act``, ``data.suite=dm_control``,
``tar-rl data import lerobot``) is looked up in a :class:`Registry`: register by name, list the
names, get or build by name; an unknown name is refused with the registered ones listed. The
recipe's Hydra config groups and the command line's choices are generated from the registries, so
adding an entry is one new module plus its ``register`` call.

It lives in ``objectives`` (the lowest layer) and imports nothing from the project, so every layer may use it.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Iterator
from typing import Generic, TypeVar

__all__ = ["Registry", "UnknownName", "did_you_mean"]

T = TypeVar("T")


def did_you_mean(name: object, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` naming the choice closest to a mistyped ``name``; ``""`` when none is close."""
    close = difflib.get_close_matches(str(name), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


class UnknownName(ValueError):
    """A name no entry of a registry has (the message lists the registered names)."""


class Registry(Generic[T]):
    """Entries of one kind by name, in registration order.

    Args:
        kind: what the entries are, for messages (``"weighting"``, ``"policy"``, ...).

    Entries with a ``build`` attribute are built by :meth:`build`: ``registry.build(name, *args)``
    is ``registry[name].build(*args)``.
    """

    def __init__(self, kind: str):
        self.kind = kind
        self._entries: dict[str, T] = {}

    def register(self, name: str, entry: T) -> T:
        """Add ``entry`` under ``name`` (a name may be registered once); returns ``entry``."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"a {self.kind} needs a non-empty name, got {name!r}")
        if name in self._entries:
            raise ValueError(f"a {self.kind} named {name!r} is registered already")
        self._entries[name] = entry
        return entry

    def names(self) -> list[str]:
        """The registered names, in registration order."""
        return list(self._entries)

    def get(self, name: str) -> T:
        """The entry called ``name``.

        Raises:
            UnknownName: no such entry; the message lists the registered names.
        """
        try:
            return self._entries[name]
        except (KeyError, TypeError):
            hint = did_you_mean(name, self._entries)
            raise UnknownName(f"unknown {self.kind} {name!r}{hint}; registered: {', '.join(self._entries)}") from None

    def build(self, name: str, *args, **kwargs):
        """``get(name).build(*args, **kwargs)``."""
        return self.get(name).build(*args, **kwargs)

    def __getitem__(self, name: str) -> T:
        return self.get(name)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def items(self):
        return self._entries.items()

    def values(self):
        return self._entries.values()

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}: {', '.join(self._entries)})"
