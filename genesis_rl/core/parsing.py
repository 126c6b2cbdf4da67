"""Depth and size limits on every file genesis-rl parses (JSON, TOML, CSV), so that a hostile or damaged file is
one line naming it, never a ``RecursionError``, a ``_csv.Error`` or memory exhausted.

Python's parsers recurse once a nesting level: ``json.loads`` and ``tomllib`` give up at about 1,000 levels with
a ``RecursionError``, and ``tomllib`` spends memory quadratic in the length of a dotted key (``a.a.a... = 1``:
8,000 segments take 260 MB, 100,000 would take tens of GB). Each file is therefore checked before it is parsed:

- its size against a ceiling (a regular file by ``stat``, without reading it; a pipe or device by reading one
  byte past the ceiling),
- its nesting by a cheap scan that skips strings (brackets inside a string do not count): JSON in C-speed byte
  operations, TOML by a tokenizer that also counts the segments of dotted keys and table headers.

The package's own files nest at most 6 levels. Each ceiling can be raised for one run by the environment
variable the error names (``GENESIS_RL_MAX_NESTING=200 genesis-rl ...``), as for :mod:`genesis_rl.core.limits`.
"""

from __future__ import annotations

import csv
import json
import re
import stat
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.limits import Limit

NESTING = Limit("NESTING", 64, "levels", "genesis-rl's own files nest at most 6 levels")
FILE_MB = Limit("FILE_MB", 256, "MiB", "records, campaign files, episode logs and schedules are far below it")
CATALOG_MB = Limit("CATALOG_MB", 2048, "MiB", "a catalog of 100,000 scenes, the scenes limit, is about 1.3 GB")
TOML_KB = Limit("TOML_KB", 1024, "KiB", "a config, rulebook or ODD is a few KiB")

#: the csv module's own limit on one cell (csv.field_size_limit()), kept: a cell of ours holds a number or a name
CSV_CELL_CHARS = csv.field_size_limit()

_UNITS = {"MiB": 1 << 20, "KiB": 1 << 10}


def _size_error(path: Path, what: str, limit: Limit, size: int | None) -> UserInputError:
    unit = _UNITS[limit.unit]
    shown = f"{size / unit:,.1f} {limit.unit}" if size is not None else f"more than {limit.value():,} {limit.unit}"
    return UserInputError(f"{what} '{path}' is {shown}, over the limit of {limit.value():,} {limit.unit} "
                          f"({limit.cost}); set {limit.variable} to raise it")


def check_size(path: Path, what: str, limit: Limit) -> None:
    """Refuse a regular file larger than ``limit`` before anything reads it (an OSError, such as a missing
    file, is left to the reader, which names the file)."""
    try:
        st = Path(path).stat()
    except OSError:
        return
    if stat.S_ISREG(st.st_mode) and st.st_size > limit.value() * _UNITS[limit.unit]:
        raise _size_error(Path(path), what, limit, st.st_size)


def read_limited(path: Path | str, what: str, limit: Limit) -> bytes:
    """A file's bytes, refused above ``limit``: by its size when it is a regular file, else (a pipe, a device
    such as /dev/zero) after reading one byte past the ceiling."""
    path = Path(path)
    check_size(path, what, limit)
    ceiling = limit.value() * _UNITS[limit.unit]
    with path.open("rb") as fh:
        data = fh.read(ceiling + 1)
    if len(data) > ceiling:
        raise _size_error(path, what, limit, None)
    return data


def decode_utf8(data: bytes, path: Path | str, what: str) -> str:
    """``data`` as text with universal newlines (as ``Path.read_text`` reads it); bytes that are not UTF-8 are a
    user error naming the file."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise UserInputError(f"{what} '{path}' is not UTF-8 text ({err.reason} at byte {err.start})") from None
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    return text


def _depth_error(where: str, depth: int | None, exact: bool = True) -> UserInputError:
    """``depth`` None: Python's parser gave up (its recursion limit, about 1,000 levels, is below a raised
    NESTING); ``exact`` False: the scan stopped as soon as it passed the limit."""
    limit = NESTING.value()
    if depth is None:
        return UserInputError(f"{where} is nested deeper than Python's parser allows (about 1,000 levels, whatever "
                              f"{NESTING.variable} = {limit:,} says)")
    shown = f"{depth:,} levels deep, over the limit of {limit:,} levels" if exact else \
        f"more than {limit:,} levels deep, the limit"
    return UserInputError(f"{where} is nested {shown} ({NESTING.cost}); set {NESTING.variable} to raise it")


# -- JSON -------------------------------------------------------------------------------------------------------
_STRUCTURAL = frozenset(b'[]{}"')
_NOT_STRUCTURAL = bytes(b for b in range(256) if b not in _STRUCTURAL)
_JSON_STRING = re.compile(rb'"[^"]*"')


def json_depth(data: bytes | str) -> int:
    """The deepest nesting of arrays and objects in JSON text, brackets inside strings not counted; linear and
    at C speed (a 1.3 GB catalog in about a second). For text that is not valid JSON the number is only a
    guess, which is harmless: the parser then reports the text's error."""
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
    if b"\\" in raw:  # escapes first, so that an escaped quote does not end a string: \\ pairs, then \"
        raw = raw.replace(b"\\\\", b"").replace(b'\\"', b"")
    kept = _JSON_STRING.sub(b"", raw.translate(None, _NOT_STRUCTURAL))
    if not kept:
        return 0
    import numpy as np

    codes = np.frombuffer(kept, dtype=np.uint8)
    steps = (np.isin(codes, (0x5B, 0x7B)).astype(np.int64)  # [ {
             - np.isin(codes, (0x5D, 0x7D)).astype(np.int64))  # ] }
    return int(max(0, np.cumsum(steps).max()))


def loads_json(text: str | bytes, where: str) -> Any:
    """``json.loads(text)`` after a depth check; ``where`` ("catalog file 'x.json'") names the text in errors.
    Invalid JSON is a UserInputError as well."""
    depth = json_depth(text)
    if depth > NESTING.value():
        raise _depth_error(where, depth)
    try:
        return json.loads(text)
    except RecursionError:  # the C decoder's own check: only with NESTING raised past Python's recursion limit
        raise _depth_error(where, None) from None
    except json.JSONDecodeError as err:
        raise UserInputError(f"{where} is not valid JSON: {err}") from None
    except UnicodeDecodeError as err:  # bytes
        raise UserInputError(f"{where} is not UTF-8 text ({err.reason} at byte {err.start})") from None


def read_json(path: Path | str, what: str = "file", limit: Limit = FILE_MB) -> Any:
    """A JSON file's content, checked for size (``limit``), UTF-8 and depth; every failure is a one-line user
    error naming the file."""
    path = Path(path)
    text = decode_utf8(read_limited(path, what, limit), path, what)
    return loads_json(text, f"{what} '{path}'")


# -- TOML -------------------------------------------------------------------------------------------------------
_TOML_TOKEN = re.compile(r'''
    (?P<str>"""(?:\\[\s\S]|[^\\])*?""""{0,2}     # multi-line basic string (1 or 2 quotes may end it)
          |\'\'\'[\s\S]*?\'\'\'\'{0,2}           # multi-line literal string
          |"(?:\\.|[^"\\\n])*"                   # basic string
          |'[^'\n]*')                            # literal string
    |(?P<skip>\#[^\n]*|[ \t\r]+)                 # comment, blanks
    |(?P<nl>\n)
    |(?P<punct>[\[\]{}=,.])
    |(?P<word>[^\s"'\#\[\]{}=,.]+)               # bare key, number, date, true, false
    |(?P<other>.)                                # an unterminated quote: tomllib reports it
''', re.VERBOSE)


def toml_depth(text: str, stop_above: int | None = None) -> int:
    """An upper estimate of how deep TOML text nests: table-header segments, dotted-key segments and open
    arrays and inline tables, strings skipped. Linear in the text; it exists because ``tomllib`` recurses once
    a bracket and spends memory quadratic in a dotted key's length, so neither may see a hostile file."""
    deepest = 0
    header = 0  # segments of the current [table] header
    in_header = False
    stack: list[int] = []  # the levels each open '[' or '{' adds: its key's segments, and one for an array
    level = 0  # sum(stack)
    brackets: list[str] = []
    key = 0  # segments of the key being read; -1 while reading a value
    pending = 0  # segments of the key whose value is being read
    for m in _TOML_TOKEN.finditer(text):
        if stop_above is not None and deepest > stop_above:
            break
        kind, tok = m.lastgroup, m.group()
        if kind == "skip":
            continue
        if kind == "nl":
            if not stack:
                in_header, key = False, 0
            continue
        if in_header:
            if tok == ".":
                header += 1
                deepest = max(deepest, 1 + header)
            continue
        if key >= 0:  # reading a key
            if tok == "[" and not stack and key == 0:
                in_header, header = True, 1
                deepest = max(deepest, 1 + header)
            elif tok == ".":
                key += 1
            elif tok == "=":
                pending, key = max(key, 1), -1
                deepest = max(deepest, 1 + header + level + pending)
            elif tok == "}" and stack:  # an empty inline table, or a comma before the brace
                level -= stack.pop()
                brackets.pop()
                key = -1
            elif kind in ("str", "word") and key == 0:
                key = 1
            continue
        if tok in ("[", "{"):  # a value that opens a container
            stack.append(pending + (tok == "["))
            level += stack[-1]
            brackets.append(tok)
            pending = 0
            deepest = max(deepest, 1 + header + level)
            if tok == "{":
                key = 0
        elif tok in ("]", "}"):
            if stack:
                level -= stack.pop()
                brackets.pop()
        elif tok == "," and brackets and brackets[-1] == "{":
            key = 0
    return deepest


def _tree_depth(value: Any) -> int:
    """How deep parsed data nests, without recursion."""
    deepest = 0
    todo: list[tuple[Any, int]] = [(value, 0)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, dict):
            children: Any = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, depth + 1)
        todo.extend((c, depth + 1) for c in children)
    return deepest


def loads_toml(text: str, where: str) -> dict[str, Any]:
    """``tomllib.loads(text)`` after a depth check; ``where`` ("config 'x.toml'") names the text in errors."""
    limit = NESTING.value()
    if toml_depth(text, stop_above=limit) > limit:
        raise _depth_error(where, limit + 1, exact=False)
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise _depth_error(where, None) from None
    except tomllib.TOMLDecodeError as err:
        raise UserInputError(f"{where} is not valid TOML: {err}") from None
    depth = _tree_depth(data)  # the scan's estimate is an upper one; this is the safety net should it miss
    if depth > limit:
        raise _depth_error(where, depth)
    return data


def read_toml_text(path: Path | str, what: str) -> str:
    """A TOML file's text, checked for size and UTF-8."""
    path = Path(path)
    return decode_utf8(read_limited(path, what, TOML_KB), path, what)


# -- CSV --------------------------------------------------------------------------------------------------------
def csv_rows(path: Path | str, what: str, encoding: str = "utf-8", limit: Limit | None = FILE_MB
             ) -> Iterator[list[str]]:
    """The rows of a CSV file; a file over ``limit``, bytes that are not text in ``encoding`` and a cell longer
    than the csv module's limit (131,072 characters) are user errors naming the file and its line."""
    path = Path(path)
    if limit is not None:
        check_size(path, what, limit)
    with path.open(newline="", encoding=encoding) as fh:
        reader = csv.reader(fh)
        try:
            yield from reader
        except csv.Error as err:
            raise UserInputError(f"{what} '{path}' line {reader.line_num}: {csv_error_reason(err)}") from None
        except UnicodeDecodeError as err:
            raise UserInputError(f"{what} '{path}' is not UTF-8 text ({err.reason} at byte {err.start})") from None


def csv_error_reason(err: csv.Error) -> str:
    """What is wrong with a CSV row, in words (the csv module's own words for the rest)."""
    text = str(err)
    if "field larger than field limit" in text:
        return (f"a cell is longer than {CSV_CELL_CHARS:,} characters, the csv module's limit (a cell here holds a "
                "number or a name)")
    return f"not a readable CSV row ({text})"
