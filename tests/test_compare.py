"""``genesis-rl compare``: policies of different campaigns paired scene by scene, and campaigns that cannot be
paired refused with the field that differs."""

from __future__ import annotations

import json
import shutil

import pytest

from genesis_rl.commands.cli import main


@pytest.fixture(scope="session")
def campaigns(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    common = ["--scenes", "3", "--steps", "40", "--seed", "4", "--no-report", "--quiet", "--workers", "1"]
    a, b = root / "a", root / "b"
    assert main(["evaluate", "--policies", "sunny,constant", "--constant-action=1,1,1,0,0", *common,
                 "--out", str(a)]) == 0
    assert main(["evaluate", "--policies", "random", *common, "--out", str(b)]) == 0
    return a, b


def _rows(folder, policy):
    return {json.loads(p.read_text())["scene"]: json.loads(p.read_text())
            for p in (folder / "episodes" / policy).glob("*.json")}


def test_compare_pairs_policies_of_two_campaigns(campaigns, tmp_path, capsys) -> None:
    a, b = campaigns
    capsys.readouterr()
    out = tmp_path / "cmp.json"
    assert main(["compare", f"fog={a}:constant", f"{b}:random", f"held={a}:sunny", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| fog - random |" in text and "| fog - held |" in text and "3 shared scenes" in text
    result = json.loads(out.read_text())
    fog, rnd = _rows(a, "constant"), _rows(b, "random")
    diffs = [fog[s]["return"] - rnd[s]["return"] for s in result["scenes"]]
    got = result["comparisons"]["fog_vs_random"]["return"]
    assert got["difference"]["mean"] == pytest.approx(sum(diffs) / 3)
    assert got["wins"] + got["ties"] + got["losses"] == 3
    assert result["policies"]["random"]["sim_steps"] == 3 * 40
    assert main(["compare", f"fog={a}:constant", f"{b}:random", "--json", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err


def test_compare_refuses_what_cannot_be_paired(campaigns, tmp_path, capsys) -> None:
    a, b = campaigns
    capsys.readouterr()
    c = tmp_path / "c"  # b's episodes, but campaign.json says its scenes ran with other episode seeds
    shutil.copytree(b, c)
    meta = json.loads((c / "campaign.json").read_text())
    meta["scenes"] = [[scene, seed + 1] for scene, seed in meta["scenes"]]
    (c / "campaign.json").write_text(json.dumps(meta))
    assert main(["compare", f"{a}:sunny", f"{c}:random"]) == 2
    assert "evaluate both with the same --seed" in capsys.readouterr().err
    assert main(["compare", f"{a}:agent", f"{b}:random"]) == 2
    assert "has no policy 'agent'; it has sunny, constant" in capsys.readouterr().err
    assert main(["compare", "just-a-folder", f"{b}:random"]) == 2
    assert "expected LABEL=CAMPAIGN:POLICY" in capsys.readouterr().err
    assert main(["compare", f"x={a}:sunny", f"x={b}:random"]) == 2
    assert "labels must differ" in capsys.readouterr().err
    meta["scenes"] = [[scene, seed - 1] for scene, seed in meta["scenes"]]
    meta["spec"]["steps"] = 80
    (c / "campaign.json").write_text(json.dumps(meta))
    assert main(["compare", f"{a}:sunny", f"{c}:random"]) == 2
    assert "differ in steps (80 against 40)" in capsys.readouterr().err
    # another package version with the same weights and settings pairs (and is named); other weights do not
    meta["spec"]["steps"] = 40
    meta["package_version"] = "0.0.1"
    meta["identity"]["system"]["version"] = "0.0.1"
    (c / "campaign.json").write_text(json.dumps(meta))
    assert main(["compare", f"{a}:sunny", f"{c}:random"]) == 0
    assert "ran with genesis-rl 0.0.1, " in capsys.readouterr().out
    meta["identity"]["system"]["weights_sha256"] = "0" * 64
    (c / "campaign.json").write_text(json.dumps(meta))
    assert main(["compare", f"{a}:sunny", f"{c}:random"]) == 2
    assert "differ in system" in capsys.readouterr().err


def test_a_policys_interval_does_not_depend_on_the_order_of_the_series(campaigns, capsys) -> None:
    a, b = campaigns
    from genesis_rl.analysis.compare import compare, parse_series

    one = compare([parse_series(f"fog={a}:constant"), parse_series(f"rnd={b}:random")])
    two = compare([parse_series(f"rnd={b}:random"), parse_series(f"fog={a}:constant")])
    assert one["policies"]["fog"]["return"] == two["policies"]["fog"]["return"]
    assert one["policies"]["rnd"]["return"] == two["policies"]["rnd"]["return"]
