"""What a shared campaign says cannot turn a command against the user: outputs onto files the campaign names,
control characters that would drive a terminal, names no file system takes, knobs the command does not know.
Each was found by the hostile sweep of shared files (tests/hostile/sweep_shared.py)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from genesis_rl.commands.cli import main
from genesis_rl.core.text import terminal_safe


@pytest.mark.parametrize("target", ["run/config.toml", "run/agent.zip", "run/catalog.json"])
def test_report_and_compare_refuse_to_write_onto_a_file_the_campaign_names(v029: Path, capsys, target: str) -> None:
    before = (v029 / target).read_bytes()
    assert main(["report", "camp", "--out", target, "--force"]) == 2
    assert f"--out '{target}'" in capsys.readouterr().err
    assert main(["compare", "a=camp:random", "b=camp:agent", "--json", target, "--force"]) == 2
    assert f"--json '{target}'" in capsys.readouterr().err
    assert (v029 / target).read_bytes() == before


def test_terminal_safe_writes_controls_as_escapes_and_keeps_what_is_asked() -> None:
    hostile = "camp\x1b]0;pwned\x07\x1b[2J\x9b1m"
    assert terminal_safe(hostile) == "camp\\x1b]0;pwned\\x07\\x1b[2J\\x9b1m"
    assert terminal_safe("a | b\nc\x1b", keep="\n") == "a | b\nc\\x1b"


def test_an_error_naming_a_hostile_file_name_prints_no_control_character(v029: Path, capsys) -> None:
    name = "cat\x1b]0;owned\x07\x1b[2J.json"
    assert main(["report", name]) == 2
    err = capsys.readouterr().err
    assert "\x1b" not in err and "\x07" not in err and "cat\\x1b]0;owned\\x07" in err


def test_the_markdown_tables_print_a_hostile_policy_name_as_text(v029: Path) -> None:
    from genesis_rl.campaigns.summary import summarize_campaign, summary_markdown

    summary = summarize_campaign(v029 / "camp", write=False)
    summary["policies"]["rand\x1b[2Jom"] = summary["policies"].pop("random")
    out = summary_markdown(summary)
    assert "\x1b" not in out and "rand\\x1b[2Jom" in out and "\n|" in out  # the table's newlines kept


def test_report_names_a_knob_it_does_not_know(v029: Path, capsys) -> None:
    path = v029 / "camp" / "campaign.json"
    meta = json.loads(path.read_text())
    meta["spec"]["env"]["knobs"] = ["fog_density", "no_such_knob"]
    path.write_text(json.dumps(meta))
    assert main(["report", "camp", "--out", "r.html"]) == 2
    assert "spec.env.knobs names 'no_such_knob', which is not a knob" in capsys.readouterr().err


def test_a_campaign_folder_whose_name_is_not_utf8_is_read(v029: Path, tmp_path: Path, capsys) -> None:
    odd = os.fsdecode(b"camp-\xff")
    shutil.copytree(v029 / "camp", odd)
    assert main(["report", odd, "--out", "r.html"]) == 0
    assert (v029 / "r.html").read_text().startswith("<!doctype html>")


def test_a_nul_byte_in_a_path_the_campaign_names_is_one_line(v029: Path, capsys) -> None:
    path = v029 / "camp" / "campaign.json"
    meta = json.loads(path.read_text())
    meta["spec"]["catalog"] = "run/cat\x00alog.json"
    path.write_text(json.dumps(meta))
    assert main(["report", "camp", "--out", "r.html"]) == 2
    assert "holds a NUL byte" in capsys.readouterr().err
