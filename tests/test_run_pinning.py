"""A run is pinned like a campaign (issue 38, family 3): run.json records the hashes of the files that decide
what a run is; train --resume, evaluate --agent and report refuse a run whose files changed, naming the file
and both hashes; an empty config.toml is refused; a run still being trained is evaluated with a warning; a
catalog's header is checked for types (``"version": true``) and its map against --map."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from builders import tiny_run

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError

TINY_RUN = tiny_run()


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict[str, Path]:
    """One tiny trained run and two small catalogs (urban and highway), shared by the tests (each copies)."""
    tmp = tmp_path_factory.mktemp("pin")
    config = tmp / "tiny.toml"
    config.write_text(TINY_RUN)
    run = tmp / "run"
    assert main(["train", "--config", str(config), "--out", str(run), "--quiet"]) == 0
    urban, highway = tmp / "urban.json", tmp / "highway.json"
    assert main(["scenes", "--map", "urban", "--count", "2", "--seed", "1", "--out", str(urban), "--quiet"]) == 0
    assert main(["scenes", "--map", "highway", "--count", "2", "--out", str(highway), "--quiet"]) == 0
    return {"run": run, "urban": urban, "highway": highway}


def _copy(made: dict[str, Path], tmp_path: Path) -> Path:
    run = tmp_path / "run"
    shutil.copytree(made["run"], run)
    return run


def _evaluate(run: Path, made: dict[str, Path], out: Path, *extra: str) -> int:
    return main(["evaluate", "--agent", str(run), "--policies", "agent", "--catalog", str(made["highway"]),
                 "--scenes", "1", "--steps", "5", "--out", str(out), "--quiet", "--no-report", *extra])


def test_a_new_run_pins_its_config_catalog_rulebook_and_weights(made, capsys) -> None:
    pins = json.loads((made["run"] / "run.json").read_text())["pins"]
    assert pins["config.toml"] == {"file": "config.toml", "sha256": _sha(made["run"] / "config.toml")}
    assert pins["catalog.json"] == {"file": "catalog.json", "sha256": _sha(made["run"] / "catalog.json")}
    # the default rulebook, no ODD, and the blind system reads no weights file
    assert pins["rulebook"] is None and pins["odd"] is None and pins["weights"] is None


def test_an_empty_config_is_refused_by_evaluate(made, tmp_path, capsys) -> None:
    """Read as TOML an empty file is every default: the built-in system, not the blind one trained against."""
    run = _copy(made, tmp_path)
    (run / "config.toml").write_text("")
    capsys.readouterr()
    assert _evaluate(run, made, tmp_path / "eval") == 2
    err = capsys.readouterr().err
    assert f"the run config '{run / 'config.toml'}' is empty" in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "eval").exists()


def test_an_edited_config_is_refused_by_train_resume_naming_it(made, tmp_path, capsys) -> None:
    run = _copy(made, tmp_path)
    pinned = _sha(run / "config.toml")
    episodes = (run / "episodes.csv").read_bytes()
    cfg = run / "config.toml"
    cfg.write_text(cfg.read_text().replace("episode_steps = 10", "episode_steps = 12"))
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume", "--steps", "80", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"'{cfg}' changed since the run was trained" in err
    assert f"run.json pins sha256 {pinned[:16]}, found {_sha(cfg)[:16]}" in err
    assert "only --steps may change" in err
    assert (run / "episodes.csv").read_bytes() == episodes  # nothing trained under the other setup
    assert json.loads((run / "checkpoints" / "last.json").read_text())["timesteps"] == 64
    # and evaluate refuses it the same way
    assert _evaluate(run, made, tmp_path / "eval") == 2
    assert f"'{cfg}' changed since the run was trained" in capsys.readouterr().err


def test_a_swapped_catalog_is_refused(made, tmp_path, capsys) -> None:
    run = _copy(made, tmp_path)
    pinned = _sha(run / "catalog.json")
    shutil.copy(made["urban"], run / "catalog.json")  # another urban catalog: valid, but not the run's
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume", "--steps", "80", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"'{run / 'catalog.json'}' changed since the run was trained (run.json pins sha256 {pinned[:16]}" in err
    assert json.loads((run / "checkpoints" / "last.json").read_text())["timesteps"] == 64
    assert _evaluate(run, made, tmp_path / "eval") == 2
    assert "catalog.json' changed since the run was trained" in capsys.readouterr().err


def test_a_resumed_run_re_pins_the_config_it_rewrites(made, tmp_path, capsys) -> None:
    """--steps raises the target: genesis-rl rewrites config.toml itself, and its pin with it."""
    run = _copy(made, tmp_path)
    assert main(["train", "--out", str(run), "--resume", "--steps", "80", "--quiet"]) == 0
    assert "total_timesteps = 80" in (run / "config.toml").read_text()
    pins = json.loads((run / "run.json").read_text())["pins"]
    assert pins["config.toml"]["sha256"] == _sha(run / "config.toml")
    capsys.readouterr()
    assert _evaluate(run, made, tmp_path / "eval") == 0
    assert "warning" not in capsys.readouterr().err


def test_a_run_still_being_trained_is_evaluated_with_a_warning_naming_its_checkpoint(made, tmp_path, capsys) -> None:
    from genesis_rl.core.files import output_folder

    run = _copy(made, tmp_path)
    (run / "agent.zip").unlink()  # training has not finished: the last checkpoint is what there is
    capsys.readouterr()
    with output_folder.hold(run):  # as train holds it while it writes
        assert _evaluate(run, made, tmp_path / "eval") == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(err) == 1
    assert "is still being trained" in err[0]
    assert "its last checkpoint is checkpoints/step_00000064.zip (step 64)" in err[0]
    assert f"evaluating '{run / 'checkpoints' / 'last.zip'}'" in err[0]
    # not held: no warning
    assert _evaluate(run, made, tmp_path / "eval2") == 0
    assert "still being trained" not in capsys.readouterr().err


def test_a_run_without_pins_loads_with_one_warning_and_resume_pins_it(made, tmp_path, capsys) -> None:
    """Runs of genesis-rl 0.10.0 wrote run.json without hashes: they stay usable, said so."""
    run = _copy(made, tmp_path)
    meta = json.loads((run / "run.json").read_text())
    del meta["pins"]
    (run / "run.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert _evaluate(run, made, tmp_path / "eval") == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(err) == 1 and "without file hashes" in err[0] and "unchecked" in err[0]
    assert main(["train", "--out", str(run), "--resume", "--quiet"]) == 0
    pins = json.loads((run / "run.json").read_text())["pins"]
    assert pins["config.toml"]["sha256"] == _sha(run / "config.toml")
    assert pins["catalog.json"]["sha256"] == _sha(run / "catalog.json")


@pytest.mark.parametrize(("pins", "message"), [
    ("yes", "field 'pins' is str 'yes', expected an object"),
    ({"config.toml": None}, "field 'pins.catalog.json' is missing"),
    ({"config.toml": {"file": "config.toml", "sha256": True}, "catalog.json": None, "rulebook": None, "odd": None,
      "weights": None}, "field 'pins.config.toml' = {'file': 'config.toml', 'sha256': True}"),
])
def test_damaged_pins_are_refused(made, tmp_path, capsys, pins, message) -> None:
    run = _copy(made, tmp_path)
    meta = json.loads((run / "run.json").read_text())
    meta["pins"] = pins
    (run / "run.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert _evaluate(run, made, tmp_path / "eval") == 2
    err = capsys.readouterr().err
    assert f"run file '{run / 'run.json'}' is damaged: {message}" in err


def test_report_refuses_a_campaign_whose_agent_run_changed(made, tmp_path, capsys) -> None:
    run = _copy(made, tmp_path)
    out = tmp_path / "eval"
    assert _evaluate(run, made, out) == 0
    with (run / "config.toml").open("a") as fh:
        fh.write("# edited\n")
    capsys.readouterr()
    assert main(["report", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"the campaign's agent run '{run}': '{run / 'config.toml'}' changed since the run was trained" in err
    assert not (out / "report.html").exists()


def test_a_changed_rulebook_or_weights_file_is_refused(tmp_path) -> None:
    """The files a run's [env] names outside its folder: rulebook, ODD, the system's weights."""
    from genesis_rl.training.pinning import check_run, write_pins

    run = tmp_path / "run"
    run.mkdir()
    rulebook, weights = tmp_path / "rules.toml", tmp_path / "w.pt"
    shutil.copy("configs/rulebook.toml", rulebook)
    weights.write_bytes(b"weights")
    (run / "config.toml").write_text(f'[env]\nrulebook = "{rulebook}"\nsystem_kwargs = {{ weights = "{weights}" }}\n'
                                     "[train]\nseed = 1\n")
    (run / "catalog.json").write_text("{}")
    write_pins(run, {"rulebook": str(rulebook), "system": "builtin", "system_kwargs": {"weights": str(weights)}})
    check_run(run, "--agent", "restore it")
    before = _sha(rulebook)
    rulebook.write_text(rulebook.read_text() + "\n# edited\n")
    with pytest.raises(UserInputError, match=f"--agent: rulebook '{rulebook}' changed since the run was trained "
                                             rf"\(run.json pins sha256 {before[:16]}"):
        check_run(run, "--agent", "restore it")
    shutil.copy("configs/rulebook.toml", rulebook)
    weights.write_bytes(b"other weights")
    with pytest.raises(UserInputError, match=f"system weights '{weights}' changed"):
        check_run(run, "--agent", "restore it")
    check_run(run, "--agent", "restore it", skip=("weights",))  # evaluate --weights replaces them on purpose
    weights.unlink()
    with pytest.raises(UserInputError, match=f"system weights '{weights}' is missing"):
        check_run(run, "--agent", "restore it")


# --- catalogs ------------------------------------------------------------------------------------------------
def test_a_catalog_of_another_map_is_refused_under_map(made, tmp_path, capsys) -> None:
    base = ["evaluate", "--policies", "sunny", "--system", "blind", "--scenes", "1", "--steps", "5", "--quiet",
            "--no-report"]
    assert main([*base, "--map", "highway", "--catalog", str(made["urban"]), "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "--map highway and --catalog" in err and "the catalog's scenes are on map 'urban'" in err
    assert not (tmp_path / "a").exists()
    # without --map the campaign is on the catalog's map, and says so
    assert main([*base, "--catalog", str(made["urban"]), "--out", str(tmp_path / "b")]) == 0
    meta = json.loads((tmp_path / "b" / "campaign.json").read_text())
    assert meta["spec"]["map"] == "urban" and meta["catalog"]["map"] == "urban"


def test_a_campaign_spec_whose_map_is_not_its_catalogs_is_refused(made, tmp_path) -> None:
    from genesis_rl.campaigns.campaign import CampaignSpec, prepare_campaign

    spec = CampaignSpec(policies=("sunny",), map="highway", catalog=str(made["urban"]), scenes=1, steps=5,
                        env={"system": "blind"})
    with pytest.raises(UserInputError, match="the catalog's scenes are on map 'urban'"):
        prepare_campaign(spec, tmp_path / "c", force=False, resume=False, progress=False)
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize(("field", "value", "message"), [
    ("version", True, "catalog field 'version' = True"),  # Python's True == 1
    ("version", 1.0, "catalog field 'version' = 1.0"),
    ("seed", -1, "field 'catalog.seed' = -1; expected an integer >= 0"),
])
def test_wrong_types_in_a_catalogs_header_are_refused(made, tmp_path, capsys, field, value, message) -> None:
    data = json.loads(made["highway"].read_text())
    data[field] = value
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(data))
    assert main(["evaluate", "--policies", "sunny", "--system", "blind", "--catalog", str(bad), "--scenes", "1",
                 "--steps", "5", "--out", str(tmp_path / "e"), "--quiet", "--no-report"]) == 2
    assert message in capsys.readouterr().err


def test_a_negative_scene_index_is_refused() -> None:
    from genesis_rl.sim.lite.scenes import generate_catalog
    from genesis_rl.world.scenes.catalog import parse_catalog

    data = json.loads(json.dumps(generate_catalog("highway", 1, 0).to_json()))
    data["scenes"][0]["index"] = -1
    with pytest.raises(UserInputError, match=r"'scenes\[0\].index' = -1"):
        parse_catalog(data)


def test_bool_versions_in_campaign_record_and_checkpoint_files_are_refused(made, tmp_path, capsys) -> None:
    """JSON's true equals 1 in Python: every header version is checked for its type as well."""
    from genesis_rl.campaigns.records import load_record

    out = tmp_path / "eval"
    assert main(["evaluate", "--policies", "sunny", "--system", "blind", "--catalog", str(made["highway"]),
                 "--scenes", "1", "--steps", "5", "--records", "all", "--out", str(out), "--quiet",
                 "--no-report"]) == 0
    record = next((out / "records").glob("*.json"))
    rec = json.loads(record.read_text())
    rec["version"] = True
    record.write_text(json.dumps(rec))
    with pytest.raises(UserInputError, match="has schema version True"):
        load_record(record)
    meta = json.loads((out / "campaign.json").read_text())
    meta["version"] = True
    (out / "campaign.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert main(["report", str(out)]) == 2
    assert "version True" in capsys.readouterr().err

    run = _copy(made, tmp_path)
    state = run / "checkpoints" / "step_00000064.state.json"
    data = json.loads(state.read_text())
    data["format"] = True
    state.write_text(json.dumps(data))
    assert main(["train", "--out", str(run), "--resume", "--steps", "80", "--quiet"]) == 2
    assert f"checkpoint file '{state}' is damaged" in capsys.readouterr().err


def test_a_campaigns_swapped_catalog_is_refused_on_resume(made, tmp_path, capsys) -> None:
    """A resumed campaign plays its remaining scenes from its catalog.json: another file would mix scenes."""
    out = tmp_path / "eval"
    argv = ["evaluate", "--policies", "sunny,random", "--system", "blind", "--catalog", str(made["highway"]),
            "--scenes", "2", "--steps", "5", "--out", str(out), "--quiet", "--no-report"]
    assert main(argv) == 0
    pinned = json.loads((out / "campaign.json").read_text())["catalog"]["sha256"]
    assert pinned == _sha(out / "catalog.json")
    shutil.rmtree(out / "episodes" / "random")  # interrupted before the random policy ran
    data = json.loads((out / "catalog.json").read_text())
    data["scenes"] = data["scenes"][::-1]  # the same scenes, in another order: scene i is another scene
    (out / "catalog.json").write_text(json.dumps(data))
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"'{out / 'catalog.json'}' changed since the campaign began (campaign.json pins sha256 {pinned[:16]}" in err
    assert not (out / "episodes" / "random").exists()


def test_a_run_json_that_is_not_a_regular_file_is_refused_not_read(made, tmp_path, capsys) -> None:
    """A FIFO in run.json's place would block a reader for ever."""
    import os

    run = _copy(made, tmp_path)
    (run / "run.json").unlink()
    os.mkfifo(run / "run.json")
    capsys.readouterr()
    assert _evaluate(run, made, tmp_path / "eval") == 2
    assert f"run file '{run / 'run.json'}' is not a regular file" in capsys.readouterr().err


def test_train_refuses_a_catalog_of_another_map_under_map(made, tmp_path, capsys) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_RUN)
    capsys.readouterr()
    assert main(["train", "--config", str(config), "--map", "highway", "--catalog", str(made["urban"]),
                 "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert "the catalog's scenes are on map 'urban'" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
