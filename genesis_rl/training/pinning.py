"""A training run pinned like a campaign: ``run.json`` records the sha256 of the files that decide what the run
is, and every command that reopens the run checks them before it believes the folder.

Pinned (``run.json``'s ``pins``, one entry each, ``{"file": ..., "sha256": ...}`` or null when the run has no
such file):

- ``config.toml`` and ``catalog.json``, the run's own copies in its folder;
- ``rulebook`` and ``odd``: the files ``env.rulebook`` and ``env.odd`` name (null: the built-in rulebook, no
  ODD);
- ``weights``: the system under test's weights, ``env.system_kwargs.weights``, else the shipped detector's for
  the built-in system (null for a system without a weights file, e.g. blind or oracle).

``train --resume``, ``evaluate --agent`` and ``report`` (for the run behind a campaign's agent) refuse a run
whose files no longer match, naming the file and both hashes (exit 2): an edited ``config.toml`` resumed would
mix two setups in one ``episodes.csv``, and an agent evaluated under another config, catalog, rulebook or
detector is not the agent that was trained. Only genesis-rl itself changes a pinned file, and it re-pins as it
does: ``train --resume --steps N`` rewrites ``config.toml``'s ``total_timesteps`` and its hash with it.

An empty (or table-less) ``config.toml`` is refused whatever ``run.json`` says: read as TOML it is all the
defaults, so the default built-in system would be evaluated instead of the one the agent trained against.

Runs written before the pins (genesis-rl 0.10.0 and earlier; ``run.json`` without ``pins``, or no
``run.json``) stay usable: they load with a one-line warning on stderr saying their files are unchecked, and
``train --resume`` pins them as they are from then on. A ``run.json`` that is not a JSON object, or whose
``pins`` are malformed (a hash that is not 64 hex digits, a bool or number where a string goes), is refused.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import stat
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.hashing import regular_file_sha256
from genesis_rl.core.files.io_utils import atomic_write_json
from genesis_rl.core.parsing import read_json

PINS = "pins"
#: what a run pins, in the order it is checked (and named in messages)
PINNED = ("config.toml", "catalog.json", "rulebook", "odd", "weights")
#: the files inside the run folder; the others are named by the run's [env]
IN_FOLDER = ("config.toml", "catalog.json")
_LABELS = {"config.toml": "config.toml", "catalog.json": "catalog.json", "rulebook": "rulebook",
           "odd": "ODD", "weights": "system weights"}
_HEX64 = re.compile(r"[0-9a-f]{64}")
_warned: set[Path] = set()  # runs whose "unpinned" warning this process has printed



def weights_file(env: Mapping[str, Any]) -> Path | None:
    """The system under test's weights file: ``system_kwargs.weights``, else the shipped detector's for the
    built-in system (the model store's yolov3-tiny weights for coco, whose ``weights`` is a folder), else None."""
    kwargs = env.get("system_kwargs") or {}
    given = kwargs.get("weights") if isinstance(kwargs, Mapping) else None
    if env.get("system") == "coco":  # a model folder: its weights file is what decides the detections
        from genesis_rl.sut.perception.model_store import model_dir

        return (Path(given) if isinstance(given, str) and given else model_dir("coco")) / "yolov3-tiny.weights"
    if isinstance(given, str) and given:
        return Path(given)
    if env.get("system", "builtin") in ("builtin", "latency"):  # latency: the built-in detector, slowed
        from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS

        return DEFAULT_WEIGHTS
    return None


def _named_files(run: Path, env: Mapping[str, Any]) -> dict[str, Path | None]:
    def setting(key: str) -> Path | None:
        value = env.get(key)
        return Path(value) if isinstance(value, str) and value else None

    return {"config.toml": run / "config.toml", "catalog.json": run / "catalog.json",
            "rulebook": setting("rulebook"), "odd": setting("odd"), "weights": weights_file(env)}


def current_pins(run: Path, env: Mapping[str, Any]) -> dict[str, dict[str, str | None] | None]:
    """The pins of ``run`` as its files are now; ``env`` is its [env] table (a mapping or ``asdict``)."""
    out: dict[str, dict[str, str | None] | None] = {}
    for name, path in _named_files(Path(run), env).items():
        out[name] = None if path is None else {
            "file": path.name if name in IN_FOLDER else str(path), "sha256": regular_file_sha256(path)}
    return out


def write_pins(run: Path, env: Mapping[str, Any]) -> None:
    """Record the run's pins in its ``run.json`` (kept, or created for a run that has none)."""
    run = Path(run)
    meta = read_run_meta(run) or {"package": "genesis-rl"}
    meta[PINS] = current_pins(run, env)
    atomic_write_json(run / "run.json", meta, indent=2)


def read_run_meta(run: Path) -> dict[str, Any] | None:
    """``run.json`` as an object, None when the run has none; a damaged one is refused, naming it."""
    path = Path(run) / "run.json"
    if not path.exists():
        return None
    if not path.is_file():  # a FIFO or a device would block or never end
        raise UserInputError(f"run file '{path}' is not a regular file; genesis-rl train writes it: restore it, or "
                             "train the run again")
    meta = read_json(path, "run file")
    if not isinstance(meta, dict):
        raise UserInputError(f"run file '{path}' is damaged: expected a JSON object, found {type(meta).__name__}")
    return meta


def _pins_of(meta: Mapping[str, Any], path: Path) -> dict[str, dict[str, Any] | None] | None:
    """``run.json``'s pins, checked field by field; None for a run written before them."""
    if PINS not in meta:
        return None
    pins = meta[PINS]

    def damaged(what: str) -> UserInputError:
        return UserInputError(f"run file '{path}' is damaged: {what}; it is written by genesis-rl train: restore "
                              "it, or train the run again")

    if not isinstance(pins, dict):
        raise damaged(f"field 'pins' is {type(pins).__name__} {pins!r}, expected an object")
    for name in PINNED:
        if name not in pins:
            raise damaged(f"field 'pins.{name}' is missing")
        entry = pins[name]
        if entry is None:
            continue
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str) or not (
                entry.get("sha256") is None
                or isinstance(entry.get("sha256"), str) and _HEX64.fullmatch(entry["sha256"])):
            raise damaged(f"field 'pins.{name}' = {entry!r}; expected null or an object with 'file' (a string) "
                          "and 'sha256' (64 hex digits or null)")
    return pins


def read_run_config(run: Path, what: str) -> dict[str, Any]:
    """The run's ``config.toml`` as TOML tables, refusing an empty one: read as it is, it would be every
    default (the built-in system, not the one the run trained against)."""
    from genesis_rl.core.config import read_toml

    path = Path(run) / "config.toml"
    data = read_toml(path, "run config")
    missing = [t for t in ("env", "train") if not isinstance(data.get(t), dict) or not data[t]]
    if missing:
        state = "is empty" if not data else f"has no [{missing[0]}] table"
        raise UserInputError(f"{what}: the run config '{path}' {state}; genesis-rl train writes every setting "
                             "there ([env], [ppo], [sac], [train]) and a run is only read with them: restore the "
                             "file, or train the run again")
    return data


def _short(sha: str | None) -> str:
    return "none" if sha is None else sha[:16]


def check_run(run: Path, what: str, remedy: str, *, skip: Iterable[str] = (),
              only: Iterable[str] | None = None, hints: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Check ``run``'s files against the pins in its ``run.json``; returns its config's TOML tables.

    ``what`` opens every message (``--resume``, ``--agent 'RUN'``, ``report``), ``remedy`` ends it. ``skip``:
    pins not checked (``evaluate --weights`` replaces the weights on purpose); ``only``: the pins checked
    (``report`` reads the run's folder only); ``hints``: a further remedy for one pin. A run without pins
    loads with a one-line warning on stderr (once per process). Raises on the first mismatch."""
    run = Path(run)
    data = read_run_config(run, what)
    meta = read_run_meta(run)
    pins = _pins_of(meta, run / "run.json") if meta is not None else None
    if pins is None:
        if run.resolve() not in _warned:
            _warned.add(run.resolve())
            why = "has no run.json" if meta is None else "has a run.json without file hashes"
            print(f"genesis-rl: warning: run '{run}' {why} (written by genesis-rl 0.10.0 or earlier): its "
                  "config.toml, catalog, rulebook and weights are used unchecked; train --resume pins them",
                  file=sys.stderr, flush=True)
        return data
    env = data["env"]
    now = current_pins(run, env)
    names = [n for n in (PINNED if only is None else only) if n not in set(skip)]
    for name in names:
        pinned, found = pins[name], now[name]
        pinned_sha = pinned["sha256"] if pinned else None
        found_sha = found["sha256"] if found else None
        if pinned_sha == found_sha:
            continue
        file = (found or pinned or {}).get("file")
        shown = f"'{run / str(file)}'" if name in IN_FOLDER else f"{_LABELS[name]} '{file}'"
        change = "is missing" if found_sha is None and found else "changed since the run was trained"
        hint = (hints or {}).get(name)
        raise UserInputError(f"{what}: {shown} {change} (run.json pins sha256 {_short(pinned_sha)}, found "
                             f"{_short(found_sha)}); {hint + '; ' if hint else ''}{remedy}")
    return data


def adopt_pins(run: Path) -> None:
    """Pin a run written before the pins (``train --resume`` does, after :func:`check_run` warned)."""
    meta = read_run_meta(run)
    if meta is None or PINS not in meta:
        write_pins(run, read_run_config(run, "--resume")["env"])


def writer_pid(folder: Path) -> str | None:
    """The pid of the genesis-rl process writing ``folder`` (holding its ``output_folder`` lock), else None.
    Probes with a shared lock, released at once; never creates the lock file."""
    from genesis_rl.core.files.output_folder import lock_path

    path = lock_path(folder)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as err:
            if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                pid = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
                return pid if pid.isdigit() else "unknown"  # the holder writes its pid; anything else is not shown
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def last_checkpoint(run: Path) -> tuple[int, str] | None:
    """The step count and file of the run's newest complete checkpoint (``checkpoints/last.json``), if any."""
    path = Path(run) / "checkpoints" / "last.json"
    try:
        meta = read_json(path, "checkpoint file") if path.is_file() else None
    except UserInputError:
        return None
    if not isinstance(meta, dict):
        return None
    steps, name = meta.get("timesteps"), meta.get("checkpoint", "last.zip")
    if type(steps) is not int or not isinstance(name, str):
        return None
    return steps, f"checkpoints/{name}"
