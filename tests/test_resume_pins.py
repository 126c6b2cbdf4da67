"""What a resume reuses is what was written: ``pins.json`` (core/files/pins.py) refuses an edited, missing or added
file by name, computes again what is gone, and a pinned rewrite killed halfway still matches; an estimate resumed
after its episodes or catalog were edited is refused; and every reader of a steps file in the package passes the
episode's step count, so a file of another length is refused from its footer."""

from __future__ import annotations

import ast
import json
import shutil
from pathlib import Path

import pytest

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files import pins as pinning
from genesis_rl.core.files.pins import Pins

PACKAGE = Path(__file__).resolve().parents[1] / "genesis_rl"


def _folder(tmp_path: Path) -> tuple[Pins, Path]:
    pins = Pins.start(tmp_path)
    stage = tmp_path / "stage"
    (stage / "episodes").mkdir(parents=True)
    (stage / "campaign.json").write_text('{"spec": 1}')
    (stage / "episodes" / "scene_0001.json").write_text('{"total": 3.0}')
    (stage / "summary.json").write_text("{}")
    return pins, stage


def _results(rel: str) -> bool:
    return rel != "summary.json"


def test_a_pinned_folder_refuses_a_changed_a_missing_and_an_added_file_by_name(tmp_path: Path) -> None:
    pins, stage = _folder(tmp_path)
    assert not pins.check(stage, _results)  # nothing pinned yet: trusted, to be pinned
    pins.record(stage, _results, spec={"seed": (1, 2)})
    assert pins.check(stage, _results) and pins.spec(stage) == {"seed": [1, 2]}
    (stage / "summary.json").write_text('{"rewritten": true}')  # not pinned: report rewrites it
    assert pins.check(stage, _results)
    row = stage / "episodes" / "scene_0001.json"
    row.write_text('{"total": 0.0}')
    with pytest.raises(UserInputError, match=rf"'{row}' changed since genesis-rl wrote it .*start again with --force"):
        pins.check(stage, _results)
    row.unlink()
    with pytest.raises(UserInputError, match=rf"'{row}' is missing"):
        pins.check(stage, _results)
    row.write_text('{"total": 3.0}')
    extra = stage / "episodes" / "scene_0002.json"
    extra.write_text("{}")
    with pytest.raises(UserInputError, match=rf"'{extra}' was not there when genesis-rl wrote"):
        pins.check(stage, _results)
    shutil.rmtree(stage)  # a stage deleted as a whole is computed again, not refused
    assert not pins.check(stage, _results)
    assert json.loads((tmp_path / "pins.json").read_text())["schema"] == "genesis-rl/pins"


def test_a_pinned_rewrite_killed_before_its_rename_leaves_a_file_its_pin_accepts(tmp_path: Path, monkeypatch) -> None:
    pins = Pins.start(tmp_path)
    path = tmp_path / "episodes.csv"
    pins.write_bytes(path, b"index\n0\n")
    assert pins.check(path)

    def killed(path: Path, writer: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(pinning, "atomic_write", killed)
    with pytest.raises(KeyboardInterrupt):
        pins.write_bytes(path, b"index\n0\n1\n")
    assert path.read_bytes() == b"index\n0\n" and pins.check(path)  # the old file, and its pin still holds
    monkeypatch.undo()
    pins.write_bytes(path, b"index\n0\n1\n")
    path.write_bytes(b"index\n0\n")  # the old content after the new one was pinned alone: an edit
    with pytest.raises(UserInputError, match="episodes.csv' changed"):
        pins.check(path)


def test_a_damaged_pins_file_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "pins.json").write_text('{"schema": "genesis-rl/pins", "entries": {"a": {"files": {"": 3}}}}')
    with pytest.raises(UserInputError, match="pins.json' is damaged.*--force"):
        Pins(tmp_path).check(tmp_path / "a")


def test_every_steps_reader_in_the_package_passes_the_episodes_step_count() -> None:
    """A steps file is read only against the count its episode row states (``read_steps(..., steps=N)``):
    checked from the footer, before any row is read."""
    missing = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.Call):
                continue
            name = getattr(node.func, "id", getattr(node.func, "attr", None))
            positional = {"read_steps": 3, "read_step_records": 2}.get(str(name))
            if positional is None:
                continue
            if len(node.args) < positional and not any(k.arg == "steps" for k in node.keywords):
                missing.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}")
    assert missing == []


# -- estimate --resume ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def estimate(tmp_path_factory) -> Path:
    """A crude estimate of two 8-step episodes on 8 urban scenes (the member's own catalog, 1,202 generated
    scenes, would take a minute; what is pinned does not depend on its size)."""
    from genesis_rl.commands.cli import main
    from genesis_rl.sim.lite import scenes

    out = tmp_path_factory.mktemp("estimate") / "est"
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(scenes.DEFAULT_COUNTS, "urban", 8)
        assert main(["estimate", "--member", "low_sun", "--method", "crude", "--steps", "8", "--episodes", "2",
                     "--quiet", "--out", str(out)]) == 0
    assert len(json.loads((out / "catalog.json").read_text())["scenes"]) == 8
    return out


RESUME = ["estimate", "--member", "low_sun", "--method", "crude", "--steps", "8", "--episodes", "3", "--quiet",
          "--resume"]


def test_an_estimate_pins_its_catalog_and_its_episodes(estimate: Path) -> None:
    entries = json.loads((estimate / "pins.json").read_text())["entries"]
    assert set(entries) == {"catalog.json", "episodes.csv"}
    from genesis_rl.core.files.hashing import file_sha256

    assert entries["episodes.csv"]["files"][""] == [file_sha256(estimate / "episodes.csv")]


@pytest.mark.parametrize("name", ["episodes.csv", "catalog.json"])
def test_an_estimate_resumed_after_its_kept_file_was_edited_is_refused(estimate: Path, tmp_path: Path, capsys,
                                                                       name: str) -> None:
    from genesis_rl.commands.cli import main

    copy = tmp_path / "est"
    shutil.copytree(estimate, copy)
    kept = copy / name
    text = kept.read_text()
    # episodes.csv: a failure turned into a success; catalog.json: one character of a scene changed
    kept.write_text(text.replace("True", "False") if "True" in text else text.replace("0", "1", 1))
    assert kept.read_text() != text
    before = {p.name: p.read_bytes() for p in copy.iterdir()}
    assert main([*RESUME, "--out", str(copy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"'{kept}' changed since genesis-rl wrote it" in err[0]
    assert "start again with --force" in err[0]
    assert {p.name: p.read_bytes() for p in copy.iterdir()} == before  # nothing played, nothing rewritten


def test_an_unedited_estimate_resumes_and_one_of_before_the_pins_is_pinned_as_found(estimate: Path,
                                                                                   tmp_path: Path) -> None:
    from genesis_rl.commands.cli import main

    copy = tmp_path / "est"
    shutil.copytree(estimate, copy)
    (copy / "pins.json").unlink()  # as written by genesis-rl before the pins
    assert main([*RESUME, "--out", str(copy)]) == 0
    assert len((copy / "episodes.csv").read_text().splitlines()) == 4
    assert set(json.loads((copy / "pins.json").read_text())["entries"]) == {"catalog.json", "episodes.csv"}
