"""Typed records that still read as the dictionaries they were made from.

A stage that moves from nested dictionaries to dataclasses names the fields it reads as attributes; keeping
the record a read-only mapping of every field it was read from (``fields``) lets the code and the users'
scripts written against the dictionaries read it unchanged.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any


class FieldsMapping(Mapping[str, Any]):
    """A read-only mapping over a record's ``fields`` (a subclass, usually a frozen dataclass, sets it)."""

    fields: Mapping[str, Any]

    def __getitem__(self, key: str) -> Any:
        return self.fields[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.fields)

    def __len__(self) -> int:
        return len(self.fields)
