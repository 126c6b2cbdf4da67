"""Weather schedules: per-step knob values from a CSV file (one row a step, one column a knob).

Knobs the file does not name keep the base weather's value. Used by ``genesis-rl drive --schedule`` and,
later, to replay an agent's weather from an edge-case record.
"""

from __future__ import annotations

import csv
from pathlib import Path

from genesis_rl.errors import UserInputError
from genesis_rl.knobs import KNOBS, Weather


def load_schedule(path: str | Path, base: Weather, steps: int) -> list[Weather]:
    """Read a schedule of exactly ``steps`` rows; errors name the file, row and knob."""
    path = Path(path)
    if not path.is_file():
        raise UserInputError(f"schedule file '{path}' does not exist")
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        columns = [c.strip() for c in (reader.fieldnames or [])]
        knobs = [c for c in columns if c != "step"]
        unknown = [c for c in knobs if c not in KNOBS]
        if not knobs or unknown:
            raise UserInputError(
                f"schedule '{path}': unknown knob column(s) {unknown or '(none given)'}; allowed: "
                f"step, {', '.join(KNOBS)}"
            )
        rows = list(reader)
    if len(rows) != steps:
        raise UserInputError(f"schedule '{path}' has {len(rows)} rows; it needs one per step ({steps})")
    out = []
    for i, row in enumerate(rows):
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
    from genesis_rl.io_utils import atomic_write

    names = knobs or list(KNOBS)

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["step", *names])
            for i, wt in enumerate(weathers):
                w.writerow([i, *(repr(float(wt[n])) for n in names)])

    atomic_write(Path(path), write)
