"""CSV cells that a spreadsheet will not run: a shared campaign's strings reach Excel or LibreOffice as text.

A cell starting with ``=``, ``+``, ``-``, ``@``, a tab or a carriage return is read as a formula by spreadsheet
tools (``=HYPERLINK(...)``, ``=1+1``). OWASP's advice for CSV injection: prefix such a text cell with a single
quote, which the tools show as text. Numbers are left alone (a negative number is a number, not a formula).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def safe_cell(value: Any) -> Any:
    """``value``, or a text cell that starts like a formula with a ``'`` before it. A number written as text
    (``-138.6``, as a CSV read back gives it) stays as it is: a spreadsheet reads it as the number."""
    if isinstance(value, str) and value.startswith(FORMULA_STARTS) and not _is_number(value):
        return "'" + value
    return value


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def safe_rows(rows: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Every row with :func:`safe_cell` applied to each value."""
    return [{k: safe_cell(v) for k, v in row.items()} for row in rows]
