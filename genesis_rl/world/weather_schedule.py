"""Weather schedules: per-step knob values from a CSV file (one row a step, one column a knob).

Knobs the file does not name keep the base weather's value. Used by ``genesis-rl drive --schedule`` and,
later, to replay an agent's weather from an edge-case record.
"""

from __future__ import annotations

import csv
from pathlib import Path

from genesis_rl.core.errors import UserInputError
from genesis_rl.world.knobs import KNOBS, Weather


def load_schedule(path: str | Path, base: Weather, steps: int) -> list[Weather]:
    """Read a schedule of exactly ``steps`` rows; errors name the file, row and knob."""
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"schedule '{path}' is a folder; expected a CSV file")
    if not path.is_file():
        raise UserInputError(f"schedule file '{path}' does not exist")
    from genesis_rl.core.parsing import csv_rows

    # utf-8-sig: a spreadsheet's byte-order mark is not part of the first column's name; size and cell length
    # are checked (a cell over the csv module's 131,072 characters is one line naming the file and line)
    table = [cells for cells in csv_rows(path, "schedule", encoding="utf-8-sig") if cells]  # blank lines: no rows
    if not table:
        raise UserInputError(f"schedule '{path}' is empty; expected a header row: step, {', '.join(KNOBS)}")
    columns = [c.strip() for c in table[0]]
    knobs = [c for c in columns if c != "step"]
    unknown = [c for c in knobs if c not in KNOBS]
    if not knobs or unknown:
        raise UserInputError(
            f"schedule '{path}': unknown knob column(s) {unknown or '(none given)'}; allowed: "
            f"step, {', '.join(KNOBS)}"
        )
    repeated = sorted({c for c in columns if columns.count(c) > 1})
    if repeated:
        raise UserInputError(f"schedule '{path}': column(s) {repeated} appear more than once")
    rows = []
    for i, cells in enumerate(table[1:]):
        if len(cells) != len(columns):
            raise UserInputError(f"schedule '{path}' row {i + 1} has {len(cells)} cells; the header has "
                                 f"{len(columns)}")
        rows.append(dict(zip(columns, cells, strict=True)))
    if len(rows) != steps:
        raise UserInputError(f"schedule '{path}' has {len(rows)} rows; it needs one per step ({steps})")
    out = []
    for i, row in enumerate(rows):
        if "step" in row and row["step"].strip() != str(i):
            raise UserInputError(f"schedule '{path}' row {i + 1}: step = '{row['step'].strip()}'; expected {i} "
                                 "(rows are steps 0, 1, 2, ... in order)")
        values = {}
        for k in knobs:
            raw = (row.get(k) or "").strip()
            try:
                values[k] = float(raw)
            except ValueError:
                raise UserInputError(f"schedule '{path}' row {i + 1}: {k} = '{raw}' is not a number") from None
        try:
            out.append(Weather.from_partial(values, base=base))
        except UserInputError as err:
            raise UserInputError(f"schedule '{path}' row {i + 1}: {err}") from None
    return out


def save_schedule(path: str | Path, weathers: list[Weather], knobs: list[str] | None = None) -> None:
    """Write a schedule that :func:`load_schedule` reads back exactly (values printed with repr)."""
    from genesis_rl.core.files.io_utils import atomic_write

    names = knobs or list(KNOBS)

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["step", *names])
            for i, wt in enumerate(weathers):
                w.writerow([i, *(repr(float(wt[n])) for n in names)])

    atomic_write(Path(path), write)
