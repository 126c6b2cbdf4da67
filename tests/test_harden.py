"""genesis-rl harden end to end on a tiny campaign: a round changes the detector's weights and records the data
it used, a resumed round gives the same weights, a retrain hook from outside the package is called with the
exported failures, and the seesaw check rejects a round that lowers clear-day recall beyond the tolerance."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.errors import UserInputError
from genesis_rl.harden.rounds import seesaw
from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS, file_sha256, load_checkpoint

pytestmark = pytest.mark.xdist_group("harden")

#: the built-in system by day in the urban ODD with the sun 5 deg up ahead: its detector never saw a sun under
#: 15 deg, and scenes 5 and 7 of this catalog (seed 0 picks them) collide within 70 steps
CONFIG = """[env]
map = "urban"
system = "builtin"
odd = "genesis_rl/sut/zoo/odd/urban_day.toml"
dynamics = "natural"
start_weather = "sun_altitude_angle=5,sun_azimuth_angle=0"
"""
BASE = ["--rounds", "1", "--test-scenes", "1", "--clear-frames", "12", "--quiet"]
SMALL = [*BASE, "--epochs", "1", "--original-frames", "16", "--validation-frames", "16"]

HOOK = '''
import json, shutil
from pathlib import Path

import torch


def blinding(request):
    """Writes what it was given, and weights whose heatmap never fires (clear-day recall falls to 0)."""
    frames = sum(1 for f in request.failures for _ in (f / "images").glob("*.jpg"))
    Path(request.work, "hook_calls.json").write_text(json.dumps({
        "round": request.round, "system": request.system, "weights": str(request.weights),
        "failures": [str(f) for f in request.failures], "frames": frames, "seed": request.seed}))
    ckpt = torch.load(request.weights, map_location="cpu", weights_only=True)
    for key, value in ckpt["state_dict"].items():
        if key.startswith("heatmap") and key.endswith("bias"):
            value.fill_(-20.0)
    request.out.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, request.out / "blind.pt")
    return request.out / "blind.pt"
'''


def held_out(attack: Path) -> list[str]:
    return ["--test-catalog", str(attack.parent / "held_out.json")]


@pytest.fixture(scope="session")
def attack(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("harden")
    (tmp / "low_sun.toml").write_text(CONFIG)
    assert main(["scenes", "--map", "urban", "--count", "8", "--seed", "0", "--out", str(tmp / "urban8.json")]) == 0
    # held-out scenes: another catalog seed (a file, so that no run generates the map's 1,202 scenes)
    assert main(["scenes", "--map", "urban", "--count", "4", "--seed", "3", "--out", str(tmp / "held_out.json")]) == 0
    out = tmp / "attack"
    assert main(["evaluate", "--config", str(tmp / "low_sun.toml"), "--policies", "sunny", "--catalog",
                 str(tmp / "urban8.json"), "--scenes", "2", "--seed", "0", "--steps", "120", "--out", str(out),
                 "--no-report", "--quiet"]) == 0
    return out


@pytest.fixture(scope="session")
def hardened(attack: Path) -> Path:
    out = attack.parent / "hard"
    assert main(["harden", str(attack), "--out", str(out), *SMALL, *held_out(attack)]) == 0
    return out


def test_a_round_retrains_the_detector_on_the_failure_frames_and_records_them(attack: Path, hardened: Path) -> None:
    result = json.loads((hardened / "harden.json").read_text())
    assert result["done"] and result["base_weights_sha256"] == file_sha256(DEFAULT_WEIGHTS)
    (rnd,) = result["rounds"]
    assert rnd["attack"]["in_odd_failures"] == 2 and rnd["attack"]["episodes"] == 2
    # only frames up to each impact (the campaign keeps 6 steps after it): fewer than the campaign kept
    kept = len(list((attack / "frames").glob("*/*/*.jpg")))
    assert 10 <= rnd["frames"] < kept
    assert rnd["weights_sha256"] != result["base_weights_sha256"]
    assert rnd["weights"] == "round_1/weights/vehicle_detector.pt"  # relative: a moved folder resumes on its own
    ckpt = load_checkpoint(hardened / rnd["weights"])
    (finetune,) = ckpt["metadata"]["finetunes"]
    assert finetune["failure_frames"] == rnd["frames"] and finetune["original_frames"] == 16
    assert rnd["export"] == "round_1/failures"
    assert finetune["failure_exports"] == ["round_1/failures"] and len(finetune["failure_sha256"]) == 64
    base = load_checkpoint(DEFAULT_WEIGHTS)
    changed = [k for k, v in ckpt["state_dict"].items() if v.is_floating_point() and
               float((v - base["state_dict"][k]).abs().max()) > 1e-6]
    assert len(changed) > 10
    # the threshold is re-picked as detector train picks it: best F1 on the detector's own validation frames
    assert finetune["validation"]["frames"] == 16 and ckpt["score_threshold"] == finetune["validation"]["threshold"]
    assert finetune["validation"]["at_old_threshold"]["threshold"] == pytest.approx(base["score_threshold"])
    assert result["baseline"]["test"]["episodes"] == 1 and rnd["test"]["episodes"] == 1
    assert rnd["clear"]["frames"] == 12 and rnd["status"] in ("accepted", "seesaw")
    assert result["final_attack"]["episodes"] == 2
    # both attack episodes collided: no near miss to add (the line is the default 1.5 s)
    assert rnd["near_misses"]["ttc_s"] == 1.5 and rnd["near_misses"]["found"] == 0
    page = (hardened / "harden.html").read_text()
    assert "harden.png" in page and rnd["weights_sha256"][:12] in page


def test_a_resumed_round_gives_the_same_weights(hardened: Path, tmp_path) -> None:
    copy = tmp_path / "hard"
    shutil.copytree(hardened, copy)
    before = json.loads((copy / "round_1" / "round.json").read_text())
    (copy / "round_1" / "round.json").unlink()
    shutil.rmtree(copy / "round_1" / "weights")
    shutil.rmtree(copy / "final_attack")
    assert main(["harden", before["attack"]["folder"], "--out", str(copy), "--resume", *SMALL,
                 *held_out(Path(before["attack"]["folder"]))]) == 0
    after = json.loads((copy / "round_1" / "round.json").read_text())
    assert after["weights_sha256"] == before["weights_sha256"]
    assert after["test"]["rate"] == before["test"]["rate"] and after["clear"] == before["clear"]


def test_a_wide_retest_added_on_resume_replays_every_rounds_weights_on_the_same_scenes(hardened: Path,
                                                                                         tmp_path) -> None:
    from genesis_rl.campaigns.summary import load_campaign

    copy = tmp_path / "hard"
    shutil.copytree(hardened, copy)
    attack = Path(json.loads((copy / "harden.json").read_text())["spec"]["campaign"])
    assert main(["harden", str(attack), "--out", str(copy), "--resume", *SMALL, *held_out(attack),
                 "--retest-scenes", "4"]) == 0
    result = json.loads((copy / "harden.json").read_text())
    rows = result["retest"]["rounds"]
    assert result["retest"]["scenes"] == 4 and [r["round"] for r in rows] == [0, 1]
    assert all(r["episodes"] == 4 for r in rows)
    # the in-loop re-test's scene is one of the four, with its episode seed: the same weights give the same episode
    for rnd, row in zip([result["baseline"], *result["rounds"]], rows, strict=True):
        _, small = load_campaign(copy / f"round_{rnd['round']}" / "test")
        _, wide = load_campaign(copy / row["folder"])
        (episode,) = small["sunny"]
        same = [e for e in wide["sunny"] if e["scene"] == episode["scene"]]
        assert len(same) == 1 and same[0]["episode_seed"] == episode["episode_seed"]
        assert same[0]["total"] == episode["total"]
    assert rows[1]["fall"] == (None if rows[0]["rate"]["rate"] == 0 else
                               pytest.approx(1 - rows[1]["rate"]["rate"] / rows[0]["rate"]["rate"], abs=1e-4))
    assert "Re-test on 4 held-out scenes" in (copy / "harden.html").read_text()


def test_a_stage_run_against_other_weights_is_replaced_not_resumed(attack: Path, tmp_path) -> None:
    """--rounds may grow on resume: the final attack then runs against the new last weights and seed, so a
    campaign of another spec in its folder is replaced (resuming it would mix two systems' episodes)."""
    from genesis_rl.campaigns.campaign_files import read_campaign_meta
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.harden.rounds import _run, attack_spec

    base = dataclasses.replace(CampaignSpec.from_json(read_campaign_meta(attack)["spec"]), scenes=1, steps=20)
    folder = tmp_path / "final_attack"
    first, later = attack_spec(base, 2, DEFAULT_WEIGHTS), attack_spec(base, 3, DEFAULT_WEIGHTS)
    _run(first, folder, 1, False)
    _run(first, folder, 1, False)  # the same spec: kept as it is
    assert CampaignSpec.from_json(read_campaign_meta(folder)["spec"]).seed == first.seed
    _run(later, folder, 1, False)
    assert CampaignSpec.from_json(read_campaign_meta(folder)["spec"]).to_json() == later.to_json()
    assert (folder / "summary.json").is_file()


def test_closest_approach_is_the_smallest_time_to_collision_inside_the_odd() -> None:
    from genesis_rl.harden.near_miss import closest_approach

    def row(step, gap, ego, lead, odd="inside"):
        return {"step": step, "true_lead_distance": gap, "ego_speed": ego, "lead_speed": lead, "odd_status": odd}

    rows = [row(1, 30.0, 10.0, 5.0),              # 6 s
            row(2, 6.0, 10.0, 5.0, "outside"),    # 1.2 s, but outside the ODD
            row(3, 2.0, 5.2, 5.0),                # closing at 0.2 m/s: no conflict
            row(4, 9.0, 12.0, 2.0),               # 0.9 s: the closest approach
            row(5, 3.0, 3.0, 4.0),                # opening
            row(6, float("inf"), 10.0, 0.0)]      # no lead
    assert closest_approach(rows) == (4, pytest.approx(0.9))
    assert closest_approach(rows[4:]) is None


def test_a_near_miss_is_replayed_for_its_frames_and_exported_with_labels(hardened: Path, tmp_path) -> None:
    """Round 1's re-test drove its scene without a collision, closing to a time to collision of 1.27 s: a near miss.
    Its frames are rendered again from the record, the same bytes twice, and exported with the simulator's boxes;
    a record that no longer drives the same episode is refused."""
    from genesis_rl.exports.dataset import export_dataset
    from genesis_rl.harden.near_miss import near_misses, render_frames

    test = hardened / "round_1" / "test"
    weights = hardened / "round_1" / "weights" / "vehicle_detector.pt"
    found = near_misses(test, 1.5)
    assert list(found) == [("sunny", 3)] and 1.0 < found[("sunny", 3)]["ttc"] <= 1.5
    assert near_misses(test, 1.0) == {} and near_misses(test, 0) == {}
    step = int(found[("sunny", 3)]["step"])
    first = render_frames(test, found, tmp_path / "a", weights, frames_before=40, stride=2)
    render_frames(test, found, tmp_path / "b", weights, frames_before=40, stride=2)
    assert first == {"episodes": ["sunny_scene_0003"], "departed": [], "unrecorded": []}
    frames = sorted((tmp_path / "a" / "frames" / "sunny" / "scene_0003").glob("*.jpg"))
    assert [f.name for f in frames] == [f"step_{s:04d}.jpg" for s in range(max(step - 40, 1), step + 1)
                                        if (step - s) % 2 == 0]
    assert all(f.read_bytes() == (tmp_path / "b" / f.relative_to(tmp_path / "a")).read_bytes() for f in frames)
    exported = export_dataset(test, "yolo", tmp_path / "export", extra_frames=tmp_path / "a",
                              keep=lambda p, s, st: (p, s) == ("sunny", 3) and st <= step)
    assert exported["images"] == len(frames) and exported["labels"] >= len(frames)
    # another world seed in the record (the seed a replay's traffic and noise come from): the replay departs
    # from the campaign's step data
    copy = tmp_path / "campaign"
    shutil.copytree(test, copy)
    record = copy / "records" / "sunny_scene_0003.json"
    data = json.loads(record.read_text())
    data["world_seed"] += 1
    record.write_text(json.dumps(data))
    with pytest.raises(UserInputError, match="replayed as the campaign recorded it"):
        render_frames(copy, found, tmp_path / "c", weights, frames_before=40, stride=2)


def test_an_outside_retrain_hook_is_called_and_the_seesaw_rejects_its_blind_weights(attack: Path, tmp_path,
                                                                                     monkeypatch) -> None:
    (tmp_path / "my_hook.py").write_text(HOOK)
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "hooked"
    assert main(["harden", str(attack), "--out", str(out), "--retrain", "my_hook:blinding", *BASE,
                 *held_out(attack)]) == 0
    call = json.loads((out / "hook_calls.json").read_text())
    assert call["round"] == 1 and call["system"] == "builtin" and call["weights"] == str(DEFAULT_WEIGHTS)
    assert call["failures"] == [str(out / "round_1" / "failures")] and call["frames"] > 0
    result = json.loads((out / "harden.json").read_text())
    (rnd,) = result["rounds"]
    assert rnd["clear"]["recall"] == 0.0
    assert rnd["status"] == "seesaw" and not rnd["seesaw"]["ok"] and "recall" in rnd["seesaw"]["why"]
    # the rejected weights are not carried on: the final attack ran the weights before the round
    assert result["final_weights"] == str(DEFAULT_WEIGHTS)


def test_seesaw_tolerance() -> None:
    before = {"precision": 0.92, "recall": 0.91}
    assert seesaw(before, {"precision": 0.915, "recall": 0.905}, 0.01)["ok"]
    assert seesaw(before, {"precision": 0.95, "recall": 0.97}, 0.01)["ok"]  # a gain is no seesaw
    check = seesaw(before, {"precision": 0.93, "recall": 0.895}, 0.01)
    assert not check["ok"] and check["drop"]["recall"] == pytest.approx(0.015) and "recall" in check["why"]
    assert seesaw(None, None, 0.01) == {"checked": False, "ok": True,
                                        "why": "the system exposes no detector to evaluate"}


@pytest.mark.parametrize("args, field", [
    (["--rounds", "0"], "rounds"),
    (["--tolerance", "2"], "tolerance"),
    (["--retrain", "nohook"], "--retrain"),
    (["--retrain", "builtin", "--epochs", "0"], "finetune.epochs"),
    (["--retrain", "not_a_module_anywhere:fn"], "not_a_module_anywhere"),
    (["--adversary", "no_such_config.toml"], "--adversary"),
    (["--test-catalog", "{attack}/../urban8.json"], "attack campaign's own catalog"),
    (["--test-catalog", "{attack}/../held_out.json", "--test-scenes", "5"], "holds 4 scenes"),
    (["--test-catalog", "{attack}/../held_out.json", "--test-scenes", "1", "--retest-scenes", "5"],
     "--retest-scenes 5"),
    (["--retest-scenes", "-1"], "--retest-scenes = -1; allowed: an integer >= 0"),
    (["--near-miss-ttc", "11"], "near_miss_ttc"),
])
def test_bad_input_exits_2_naming_the_field(attack: Path, tmp_path, capsys, args, field) -> None:
    args = [a.replace("{attack}", str(attack)) for a in args]
    assert main(["harden", str(attack), "--out", str(tmp_path / "x"), *args]) == 2
    assert field in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_out_inside_the_campaign_is_refused(attack: Path, capsys) -> None:
    assert main(["harden", str(attack), "--out", str(attack / "hard")]) == 2
    assert "hard" in capsys.readouterr().err


def test_a_member_of_another_system_or_map_is_refused(attack: Path, tmp_path, capsys) -> None:
    assert main(["harden", str(attack), "--out", str(tmp_path / "x"), "--member", "low_sun_highway",
                 "--estimate-episodes", "4"]) == 2
    err = capsys.readouterr().err
    assert "--member low_sun_highway" in err and "map" in err
    assert main(["harden", str(attack), "--out", str(tmp_path / "x"), "--estimate-episodes", "4"]) == 2
    assert "--member" in capsys.readouterr().err


def test_a_member_is_matched_by_its_odd_text_not_its_path(attack: Path, tmp_path) -> None:
    """The same ODD file in another checkout is the member's ODD; a changed copy is not."""
    from genesis_rl.campaigns.campaign_files import read_campaign_meta
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.harden.rounds import check_member

    base = CampaignSpec.from_json(read_campaign_meta(attack)["spec"])
    copy = tmp_path / "urban_day.toml"
    copy.write_bytes(Path(base.env["odd"]).read_bytes())
    check_member("low_sun", dataclasses.replace(base, env={**base.env, "odd": str(copy)}))
    copy.write_text(copy.read_text() + "\n# changed\n")
    with pytest.raises(UserInputError, match="its odd"):
        check_member("low_sun", dataclasses.replace(base, env={**base.env, "odd": str(copy)}))


def test_an_estimate_runs_the_member_with_the_given_weights(tmp_path) -> None:
    from genesis_rl.estimation.run import EstimateSpec, env_config

    own = env_config(EstimateSpec(member="low_sun", method="crude", episodes=4), tmp_path / "c.json")
    assert "weights" not in own["system_kwargs"]
    spec = EstimateSpec(member="glare_blind", method="crude", episodes=4, weights=str(DEFAULT_WEIGHTS))
    assert env_config(spec, tmp_path / "c.json")["system_kwargs"]["weights"] == str(DEFAULT_WEIGHTS.resolve())
    assert spec.to_json()["weights"] == str(DEFAULT_WEIGHTS)


# -- what --resume reuses is what was written (pins.json) ---------------------------------------------------------
def _edit(path: Path) -> None:
    """Change a kept file as a colleague's script or a careless hand would: a number, a row, a byte."""
    if path.name == "campaign.json":
        data = json.loads(path.read_text())
        data["spec"]["seed"] += 1
        path.write_text(json.dumps(data))
    elif path.suffix == ".json":
        data = json.loads(path.read_text())
        data["edited"] = True
        path.write_text(json.dumps(data))
    elif path.suffix == ".jsonl":
        lines = path.read_text().splitlines()
        path.write_text("\n".join(lines[:-1]) + "\n")
    elif path.suffix == ".parquet":
        import pyarrow.parquet as pq

        table = pq.read_table(path)
        pq.write_table(table.slice(0, table.num_rows - 1), path)
    else:
        path.write_bytes(path.read_bytes() + b"\0")


def _refused(capsys, name: Path) -> None:
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"'{name}'" in line and "start again with --force" in line, line


@pytest.mark.parametrize("kept", [
    "round_0/round.json",  # the baseline, kept
    "round_1/round.json",  # a kept round
    "round_1/weights/vehicle_detector.pt",  # the weights a kept round made: the rounds after it start from them
    "round_1/failures/metadata.jsonl",  # a kept round's failure export: the rounds after it retrain on it too
    "final_attack/campaign.json",  # a kept stage campaign: its spec
    "final_attack/episodes/sunny/scene_*.json",  # ... an episode
    "final_attack/steps/sunny/scene_*.parquet",  # ... its steps
])
def test_a_kept_file_edited_before_the_resume_is_refused_by_name(attack: Path, hardened: Path, tmp_path, capsys,
                                                                  kept: str) -> None:
    copy = tmp_path / "hard"
    shutil.copytree(hardened, copy)
    path = sorted(copy.glob(kept))[0]
    _edit(path)
    assert main(["harden", str(attack), "--out", str(copy), "--resume", *SMALL, *held_out(attack)]) == 2
    _refused(capsys, path)


def test_rendered_data_edited_before_a_round_retrains_on_it_is_refused(attack: Path, hardened: Path, tmp_path,
                                                                       capsys) -> None:
    """original_data.npz (validation_data.npz is read through the same function, after the training)."""
    cache = "original_data.npz"
    copy = tmp_path / "hard"
    shutil.copytree(hardened, copy)
    (copy / "round_1" / "round.json").unlink()  # round 1 runs again, from its kept export, and retrains
    shutil.rmtree(copy / "round_1" / "weights")
    _edit(copy / cache)
    assert main(["harden", str(attack), "--out", str(copy), "--resume", *SMALL, *held_out(attack)]) == 2
    _refused(capsys, copy / cache)


def test_the_attack_campaign_or_the_weights_changed_since_the_start_are_refused(attack: Path, hardened: Path,
                                                                                tmp_path, capsys) -> None:
    copy = tmp_path / "hard"
    shutil.copytree(hardened, copy)
    row = sorted((attack / "episodes" / "sunny").glob("scene_*.json"))[0]
    original = row.read_bytes()
    try:
        _edit(row)
        assert main(["harden", str(attack), "--out", str(copy), "--resume", *SMALL, *held_out(attack)]) == 2
        _refused(capsys, row)
    finally:
        row.write_bytes(original)
    result = json.loads((copy / "harden.json").read_text())
    result["base_weights_sha256"] = "0" * 64  # as if the weights the campaign names had been replaced since
    (copy / "harden.json").write_text(json.dumps(result))
    assert main(["harden", str(attack), "--out", str(copy), "--resume", *SMALL, *held_out(attack)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"the weights '{DEFAULT_WEIGHTS}' changed since the hardening" in line and "--force" in line


def test_a_stage_campaign_is_checked_against_its_pins_and_replaced_only_when_its_spec_moved(attack: Path,
                                                                                          tmp_path) -> None:
    from genesis_rl.campaigns.campaign_files import read_campaign_meta
    from genesis_rl.campaigns.campaign_spec import CampaignSpec
    from genesis_rl.campaigns.layout import CampaignFolder
    from genesis_rl.core.files.pins import Pins
    from genesis_rl.harden.rounds import _run, attack_spec

    base = dataclasses.replace(CampaignSpec.from_json(read_campaign_meta(attack)["spec"]), scenes=1, steps=20)
    pins = Pins.start(tmp_path)
    folder = tmp_path / "final_attack"
    first, later = attack_spec(base, 2, DEFAULT_WEIGHTS), attack_spec(base, 3, DEFAULT_WEIGHTS)
    _run(first, folder, 1, False, pins)
    assert pins.check(folder, CampaignFolder.holds_results)
    meta = folder / "campaign.json"
    written = meta.read_bytes()
    _edit(meta)
    with pytest.raises(UserInputError, match=f"'{meta}' changed since genesis-rl wrote it"):
        _run(first, folder, 1, False, pins)
    # a campaign interrupted before its end is pinned by the spec harden started it with
    meta.write_bytes(written)
    pins.note_spec(folder, first.to_json())
    _edit(meta)
    with pytest.raises(UserInputError, match=f"'{meta}' holds other settings than harden started this campaign "
                                             r"with \(seed\)"):
        _run(first, folder, 1, False, pins)
    meta.write_bytes(written)
    _run(later, folder, 1, False, pins)  # a resume that moved the stage (more rounds): replaced, pinned anew
    assert CampaignSpec.from_json(read_campaign_meta(folder)["spec"]).to_json() == later.to_json()
    assert pins.spec(folder) == json.loads(json.dumps(later.to_json()))
