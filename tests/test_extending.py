"""Extending GENESIS-RL from outside the package (docs/extending.md): each extension point is exercised
here by a module in tests/plugins/, which the package does not know about."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from genesis_rl.analysis.report import build_report
from genesis_rl.campaigns.campaign import CampaignSpec, run_campaign
from genesis_rl.campaigns.records import load_record, replay_record
from genesis_rl.core.errors import UserInputError
from genesis_rl.loop.rules.reward import PaperReward, RewardConfig
from genesis_rl.loop.rules.rulebook import load_rulebook
from genesis_rl.world.step_record import synthetic_step

PLUGINS = Path(__file__).parent / "plugins"
RULEBOOK = """
[[rules]]
name = "collision"
priority = 1

[[rules]]
name = "user_extensions:Speeding"   # a rule from the user's own module, by import path
priority = 2
params = { limit = 1.0 }

[[rules]]
name = "proximity"
priority = 3
"""


@pytest.fixture()
def plugins_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(PLUGINS))


def test_a_rule_by_import_path_is_loaded_checked_and_weighted(tmp_path, plugins_on_path) -> None:
    path = tmp_path / "rulebook.toml"
    path.write_text(RULEBOOK)
    rb = load_rulebook(path)
    assert rb.names == ["collision", "speeding", "proximity"]
    assert rb.step_terms(synthetic_step(ego_speed=4.5)) == {"collision": 0.0, "speeding": 3.5, "proximity": 0.0}
    # the rulebook as data carries the plug-in's path, so a record replays it without the TOML
    assert rb.describe()[1] == {"priority": 2, "name": "speeding", "params": {"limit": 1.0},
                                "path": "user_extensions:Speeding", "unit": "m/s", "in_total": True}
    # the reward weights rules by name: a weight on speeding joins the log term ...
    reward = PaperReward(RewardConfig(rule_weights={"speeding": 10.0}), rb)
    assert reward.terms(1.0, {"collision": 0.0, "speeding": 3.5, "proximity": 0.0})["reward_behaviour"] == \
        pytest.approx(math.log1p(35.0))
    # ... and a weight on a rule the rulebook lacks fails when the reward is built, naming the rule
    with pytest.raises(UserInputError, match=r"weights rule\(s\) \['rss_deficit'\] that the rulebook lacks"):
        PaperReward(RewardConfig(rule_weights={"rss_deficit": 1.0}), rb)
    path.write_text(RULEBOOK.replace("user_extensions:Speeding", "user_extensions:Nope"))
    with pytest.raises(UserInputError, match="module 'user_extensions' has no class 'Nope'"):
        load_rulebook(path)


@pytest.mark.render
def test_user_rule_and_registered_policy_reach_every_result_with_two_workers(tmp_path, plugins_on_path) -> None:
    """A rule from a user module appears in the episode rows, episodes.csv, summary.json, report.html, the step
    Parquet and the records, and replays; a policy registered with @register_policy in a user module runs in
    spawned workers (--workers 2), which only knew built-in names before."""
    import user_extensions  # noqa: F401 - registers fog_ramp, as a user's script would

    rulebook = tmp_path / "rulebook.toml"
    rulebook.write_text(RULEBOOK)
    spec = CampaignSpec(policies=("sunny", "fog_ramp"), scenes=2, steps=40, seed=0, records="all",
                        env={"rulebook": str(rulebook)})
    folder = tmp_path / "camp"
    summary = run_campaign(spec, folder, workers=2, progress=False)

    rows = {p: [json.loads(f.read_text()) for f in sorted((folder / "episodes" / p).glob("*.json"))]
            for p in spec.policies}
    assert all(len(r) == 2 for r in rows.values())
    speeding = [e["speeding"] for eps in rows.values() for e in eps]
    assert min(speeding) > 0  # the ego drives faster than 1 m/s within 2 s
    for eps in rows.values():
        for e in eps:
            assert list(e["violations"]) == ["collision", "speeding", "proximity"]
            assert e["total"] == pytest.approx(e["collision"] + e["speeding"] + e["proximity"], abs=1e-5)
    with (folder / "episodes.csv").open() as fh:
        header = next(csv.reader(fh))
    assert header[4:8] == ["collision", "speeding", "proximity", "total"]
    mean = sum(e["speeding"] for e in rows["sunny"]) / 2
    assert summary["policies"]["sunny"]["speeding"]["mean"] == pytest.approx(mean, abs=1e-6)
    steps = pq.read_table(folder / "steps" / "sunny" / sorted((folder / "steps" / "sunny").iterdir())[0].name)
    assert "rule_speeding" in steps.column_names
    assert sum(steps["rule_speeding"].to_pylist()) == pytest.approx(rows["sunny"][0]["speeding"], abs=1e-5)

    report = build_report(folder, force=True).read_text()
    assert "speeding [m/s]" in report
    assert f"{mean:.2f}" in report

    record_path = folder / rows["fog_ramp"][0]["record"]
    record = load_record(record_path)
    assert record["rulebook"][1]["path"] == "user_extensions:Speeding"
    assert record["summary"]["speeding"] == rows["fog_ramp"][0]["speeding"]
    replay = replay_record(record, keep_frames=False)
    assert replay["reproduced"] and replay["violations"]["speeding"] == pytest.approx(record["violations"]["speeding"])
    # the policy really ran: fog rose 5 per step from 0 to its maximum
    fog = [r.knobs["fog_density"] for r in replay["records"]]
    assert fog[:3] == [5.0, 10.0, 15.0] and fog[-1] == 100.0


# -- a knob -----------------------------------------------------------------------------------------------
@pytest.fixture()
def user_knob(plugins_on_path):
    """Declare the user's knob for one test, and take it back after (it would add a column everywhere)."""
    import importlib
    import sys

    from genesis_rl.world.knobs import KNOB_MODULES, KNOBS

    module = importlib.import_module("user_knob")
    yield module.LENS_DIRT
    KNOBS.pop("lens_dirt", None)
    KNOB_MODULES.pop("lens_dirt", None)
    sys.modules.pop("user_knob", None)


def test_a_knob_declared_once_reaches_weather_and_the_contact_sheet(user_knob) -> None:
    from genesis_rl.commands.render import sweep_rows
    from genesis_rl.world.knobs import KnobActionMapper, Weather, parse_weather

    assert Weather.default()["lens_dirt"] == 0.0
    assert parse_weather("lens_dirt=40")["lens_dirt"] == 40.0
    with pytest.raises(UserInputError, match=r"knob 'lens_dirt' = 140.0 is out of range; allowed 0..100 %"):
        parse_weather("lens_dirt=140")
    mapper = KnobActionMapper(("fog_density", "lens_dirt"))
    assert mapper.apply(Weather.default(), [0.0, 1.0])["lens_dirt"] == 5.0  # 5 % of its range per step
    rows = dict(sweep_rows())
    assert [title for title, _ in rows["lens_dirt"]] == ["lens_dirt=0", "lens_dirt=50", "lens_dirt=100"]
    # a recorded weather from before the knob existed reads it at its default
    assert Weather.from_recorded({"fog_density": 30.0})["lens_dirt"] == 0.0


@pytest.mark.render
def test_a_user_knob_is_turned_drawn_and_recorded_by_the_env(user_knob) -> None:
    from genesis_rl.env.genesis_env import GenesisEnv

    def frame_after(action):
        env = GenesisEnv(map="highway", scenes=2, knobs=("fog_density", "lens_dirt"), episode_steps=4,
                         camera_width=96, camera_height=72, obs_width=48, obs_height=36, system="oracle")
        try:
            env.reset(seed=0)
            for _ in range(4):
                _, _, _, _, info = env.step(np.asarray(action, np.float32))
            return env.camera_frame().astype(float), info, env.records[-1]
        finally:
            env.close()

    clean, _, _ = frame_after([0.0, 0.0])
    dirty, info, rec = frame_after([0.0, 1.0])
    assert info["knobs"]["lens_dirt"] == 20.0 and rec.knobs["lens_dirt"] == 20.0
    assert "lens_dirt" in rec.to_row()
    h, w = clean.shape[:2]
    # the hook darkened the corners (up to 12 % at 20 %), not the centre
    corner = dirty[: h // 6, : w // 6].mean() / clean[: h // 6, : w // 6].mean()
    centre = dirty[h // 3: 2 * h // 3, w // 3: 2 * w // 3].mean() / clean[h // 3: 2 * h // 3, w // 3: 2 * w // 3].mean()
    assert 0.86 < corner < 0.95 and centre > 0.97


@pytest.mark.render
def test_a_user_knob_module_named_in_genesis_rl_plugins_reaches_the_command_line(tmp_path, monkeypatch,
                                                                                user_knob, capsys) -> None:
    """``GENESIS_RL_PLUGINS`` imports a user's modules before the command line is read; ``env.plugins`` does
    the same for an env (and for training's env processes, which build their env from the config)."""
    from genesis_rl.commands.cli import main
    from genesis_rl.env.genesis_env import EnvConfig

    monkeypatch.setenv("GENESIS_RL_PLUGINS", "user_knob")
    assert main(["render", "--map", "highway", "--scene", "0", "--weather", "lens_dirt=60", "--width", "64",
                 "--height", "48", "--out", str(tmp_path / "r")]) == 0
    assert json.loads((tmp_path / "r" / "boxes.json").read_text())["weather"]["lens_dirt"] == 60.0
    monkeypatch.setenv("GENESIS_RL_PLUGINS", "user_knob,no_such_module_xyz")
    assert main(["render", "--out", str(tmp_path / "x")]) == 2
    assert "GENESIS_RL_PLUGINS: cannot import module 'no_such_module_xyz'" in capsys.readouterr().err
    assert EnvConfig(plugins=("user_knob",), knobs=("fog_density", "lens_dirt")).knobs[1] == "lens_dirt"
    with pytest.raises(UserInputError, match="env.plugins: cannot import module 'nope_xyz'"):
        EnvConfig(plugins=("nope_xyz",))


@pytest.mark.render
def test_a_record_from_before_a_knob_existed_replays_with_it_at_its_default(request, tmp_path) -> None:
    """The 0.4.0 record (tests/data) knows nothing of lens_dirt; with the knob declared it replays exactly as
    without it, bit for bit, the knob at its default (so its hook never runs), and the new telemetry carries
    the knob's column. (Against the recorded digest itself only on a CPU like the one that wrote it: see
    tests/test_compat.py; the violations agree to 1e-9 on any.)"""
    record = load_record(Path(__file__).parent / "data" / "campaign_0.4.0" / "records" / "sunny_scene_0000.json")
    assert "lens_dirt" not in record["knobs"]
    without = replay_record(record, keep_frames=False)
    request.getfixturevalue("user_knob")  # now the knob is declared
    replay = replay_record(record, keep_frames=False)
    assert replay["step_digest"] == without["step_digest"] and replay["violations"] == without["violations"]
    if replay["render_version"] == replay["recorded_render_version"]:  # else the pixels differ (test_compat)
        assert all(abs(replay["violations"][k] - v) <= 1e-9 * max(1.0, abs(v))
                   for k, v in record["violations"].items())
    assert replay["reproduced"] == without["reproduced"]
    assert {r.knobs["lens_dirt"] for r in replay["records"]} == {0.0}
    assert all("lens_dirt" not in r.knobs for r in without["records"])
