"""A second hostile-input sweep: the families the 0.30.0 probe found, on the commands and files added since
issue 38 (benchmark, zoo sweep, estimate, harden, the manifest of hashes behind ``--force``).

    PYTHONPATH=$PWD .venv/bin/python tests/hostile/sweep_shared.py --work /tmp/sweep-shared --jobs 2 \\
        --out sweep_shared.json --markdown docs/reliability/sweep_shared.md [--ids ID,ID] [--family N] [--list]

It reuses the harness of ``tests/hostile/sweep_files.py`` (fixtures, one folder a case, the same oracle:
code-exec, data-loss, abort, traceback, timeout, wrong-exit) and defines only new cases, in seven families:

* 7 (a) the same floats in every mode: one command run two ways (1 and 2 workers, in-process and pool, local and
  Ray, interrupted and resumed against uninterrupted), its result files compared to the bit;
* 8 (b) an output onto a file that an input names (a campaign's agent run, catalog, ODD, rulebook, weights in
  ``system_kwargs``; an estimate's or hardening's named files);
* 9 (c) ``--force`` by the manifest: a user's file under one of our names, a hand-edited file of ours, a damaged,
  missing or linked manifest, a stale lock, in every kind of output folder;
* 10 (d) escaping at every boundary: HTML pages, CSV cells, matplotlib text, XML, and the terminal (a raw ESC
  byte from a file or an argument echoed to stdout/stderr);
* 11 (e) sizes a file claims: zip members, npz array headers, Parquet row counts, deep or endless files;
* 12 (f) resume of benchmark, sweep, estimate and harden folders with edited specs; import paths in files that
  name modules outside the plug-in layers, or things inside them that are not plug-ins;
* 13 (g) smaller: ``--out x/``, output to a full device, signals then ``--resume``, ``--smoke`` with matrix
  flags, odd numbers for every count flag, odd bytes in paths and names.

One outcome is added to the oracle: ``unescaped``, a hostile string that reached an output file (HTML, CSV,
XML) or the terminal as it was written, where the command otherwise passed. A case of family 7 fails as
``wrong-exit`` with the first differing value named.
"""

# ruff: noqa: E501 - the cases are a table, one a line
from __future__ import annotations

import csv
import importlib.util
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("hostile_sweep", HERE / "sweep_files.py")
assert _spec and _spec.loader
hs = importlib.util.module_from_spec(_spec)
sys.modules["hostile_sweep"] = hs  # dataclasses look their module up by name
_spec.loader.exec_module(hs)

case, chain, cp, write, edit_json, edit_text, symlink = hs.case, hs.chain, hs.cp, hs.write, hs.edit_json, hs.edit_text, hs.symlink
set_path, toml_set, config, deep_json, deep_toml = hs.set_path, hs.toml_set, hs.config, hs.deep_json, hs.deep_toml
REJECT, OK, EITHER, PY = hs.REJECT, hs.OK, hs.EITHER, hs.PY
Setup = hs.Setup

FAMILIES = {
    7: "(a) the same floats in every mode",
    8: "(b) an output onto a file an input names",
    9: "(c) --force by the manifest",
    10: "(d) escaping at every boundary",
    11: "(e) sizes a file claims",
    12: "(f) resume and the import gate",
    13: "(g) smaller: paths, devices, signals, flags",
}
OUTCOMES = ("pass", "code-exec", "data-loss", "abort", "traceback", "timeout", "wrong-exit", "unescaped")

# -- payloads --------------------------------------------------------------------------------------------------
IMG = "<img src=x onerror=alert(1)>"
SCRIPT = "</pre></code><script>alert(1)</script>"
SVG = "<svg onload=alert(1)>"  # a policy name is a folder name: no slash
MATH = "$\\undefinedcmd{x}$"
FORMULAS = ("=HYPERLINK(\"http://x\",\"y\")", "+1+cmd|' /C calc'!A0", "-2+3", "@SUM(1+1)", "\tx=1", "\rx=1")
ESC = "\x1b]0;pwned\x07\x1b[2J"
CTRL = "agent\x01\x0b\x1b[31m"

# -- per-case checks after the harness's own judgement -----------------------------------------------------------
#: case id -> a check on the finished case folder and the command's full stdout/stderr: (outcome, detail) or None
CHECKS: dict[str, Callable[[Path, str, str], tuple[str, str] | None]] = {}
#: case folder -> (stdout, stderr) of every command run there (the harness keeps only the last line)
_OUTPUTS: dict[Path, list[tuple[str, str]]] = {}
_orig_run = hs._run
_orig_run_case = hs.run_case
_orig_make_fixtures = hs.make_fixtures


def _run(cmd: list[str], d: Path, env: dict[str, str], c: Any) -> tuple[int | None, str, str, float]:
    code, out, err, secs = _orig_run(cmd, d, env, c)
    _OUTPUTS.setdefault(d, []).append((out, err))
    return code, out, err, secs


def run_case(c: Any, work: Path, fx: Path, ports: dict[str, int]) -> dict[str, Any]:
    d = work / "cases" / c.id
    _OUTPUTS.pop(d, None)
    row = _orig_run_case(c, work, fx, ports)
    outs = _OUTPUTS.pop(d, [])
    out = "".join(o for o, _ in outs)
    err = "".join(e for _, e in outs)
    if c.raw is not None and row["outcome"] == "wrong-exit":  # a family-7 script: say what differed
        said = [ln for ln in err.splitlines() if ln.startswith("genesis-rl sweep:")]
        if said:
            row["detail"] = said[-1][len("genesis-rl sweep: "):][:300]
    check = CHECKS.get(c.id)
    if check is not None and row["outcome"] not in ("skipped", "code-exec") and d.is_dir():
        found = check(d, out, err)
        if found is not None and (found[0] == "data-loss" or row["outcome"] in ("pass", "wrong-exit")):
            if found[0] == "data-loss" or row["outcome"] == "pass":
                row["outcome"], row["detail"] = found
            else:
                row["detail"] = (row["detail"] + "; also " + found[1])[:300]
    return row


def _texts(d: Path, globs: tuple[str, ...]) -> list[tuple[Path, str]]:
    found = []
    for g in globs:
        for p in sorted(d.glob(g)):
            if p.is_file() and not p.is_symlink():
                found.append((p, p.read_bytes().decode("utf-8", "replace")))
    return found


def raw_in(globs: tuple[str, ...], *payloads: str) -> Callable[[Path, str, str], tuple[str, str] | None]:
    """Unescaped when a written file matching ``globs`` holds a payload as it was given."""
    def check(d: Path, out: str, err: str) -> tuple[str, str] | None:
        for p, text in _texts(d, globs):
            for s in payloads:
                if s in text:
                    return "unescaped", f"{p.relative_to(d)} holds {s[:40]!r} as given"
        return None
    return check


def in_tag(globs: tuple[str, ...], payload: str) -> Callable[[Path, str, str], tuple[str, str] | None]:
    """Unescaped when ``payload`` stands inside a tag (an attribute's text that a quote broke out of); in a text
    node a quote is harmless."""
    pattern = re.compile(r"<[^<>]*" + re.escape(payload))

    def check(d: Path, out: str, err: str) -> tuple[str, str] | None:
        for p, text in _texts(d, globs):
            m = pattern.search(text)
            if m:
                return "unescaped", f"{p.relative_to(d)} holds {payload!r} inside a tag: {m.group(0)[-80:]!r}"
        return None
    return check


def formula_cells(globs: tuple[str, ...]) -> Callable[[Path, str, str], tuple[str, str] | None]:
    """Unescaped when a CSV cell starts like a formula (= + - @ tab CR) and is not a number."""
    def check(d: Path, out: str, err: str) -> tuple[str, str] | None:
        for p, text in _texts(d, globs):
            for row in csv.reader(io.StringIO(text, newline="")):
                for cell in row:
                    if cell[:1] in ("=", "+", "-", "@", "\t", "\r") and not re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?|[-+]?(inf|nan)", cell.strip()):
                        return "unescaped", f"{p.relative_to(d)} has the cell {cell[:40]!r}"
        return None
    return check


def well_formed_xml(globs: tuple[str, ...]) -> Callable[[Path, str, str], tuple[str, str] | None]:
    def check(d: Path, out: str, err: str) -> tuple[str, str] | None:
        import xml.dom.minidom

        files = _texts(d, globs)
        for p, text in files:
            bad = [ch for ch in text if ord(ch) < 32 and ch not in "\t\n\r"]
            if bad:
                return "unescaped", f"{p.relative_to(d)} holds control character {bad[0]!r}"
            try:
                xml.dom.minidom.parseString(text.encode())
            except Exception as exc:  # noqa: BLE001 - any parse failure is the finding
                return "unescaped", f"{p.relative_to(d)} is not well-formed XML: {exc}"[:200]
        return None
    return check


def terminal(d: Path, out: str, err: str) -> tuple[str, str] | None:
    """Unescaped when a raw ESC or BEL byte reached stdout or stderr (a file's or an argument's text)."""
    for name, text in (("stdout", out), ("stderr", err)):
        for ch in ("\x1b", "\x07"):
            if ch in text:
                at = text.index(ch)
                return "unescaped", f"{name} holds a raw {ch!r}: ...{text[max(0, at - 60):at + 10]!r}"
    return None


def both(*checks: Callable[[Path, str, str], tuple[str, str] | None]) -> Callable[[Path, str, str], tuple[str, str] | None]:
    def check(d: Path, out: str, err: str) -> tuple[str, str] | None:
        for c in checks:
            found = c(d, out, err)
            if found:
                return found
        return None
    return check


def kept(*rels: str) -> Callable[[Path, str, str], tuple[str, str] | None]:
    """Data loss when a user's file is gone or changed (its content is recorded in ``SEEN`` by ``remember``)."""
    def check(d: Path, out: str, err: str) -> tuple[str, str] | None:
        for rel in rels:
            want = _SEEN.get((str(d), rel))
            p = d / rel
            if want is not None and (not p.exists() or p.read_bytes() != want):
                return "data-loss", f"the user's {rel} is {'gone' if not p.exists() else 'changed'}"
        return None
    return check


_SEEN: dict[tuple[str, str], bytes] = {}


def remember(*rels: str) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        for rel in rels:
            _SEEN[(str(d), rel)] = (d / rel).read_bytes()
    return setup


def add(fam: int, cid: str, what: str, argv: str | list[str], check: Callable[..., Any] | None = None, **kw: Any) -> None:
    case(fam, cid, what, argv, **kw)
    if check is not None:
        CHECKS[hs.CASES[-1].id] = check


# -- extra fixtures --------------------------------------------------------------------------------------------
BM_ARGS = "benchmark --members oracle_highway --policies sunny,constant --trials 1 --scenes 1 --steps 20 --reruns 1 --quiet"
#: a valid --nominal for oracle_highway: one table per held knob
NOMINAL = "".join(f"[start.{k}]\nlow = {lo}\nhigh = {hi}\n" for k, lo, hi in (("precipitation_deposits", 0, 60), ("sun_altitude_angle", 0, 90), ("sun_bearing", -180, 180)))
EST_ARGS = "estimate --member oracle_highway --method crude --episodes 4 --steps 20 --quiet"
ZS_ARGS = "zoo sweep oracle_highway --knob fog_density --values 0,60 --scenes 1 --steps 20 --quiet"
DRIVE_DV = "drive --catalog cat.json --steps 5 --system blind --no-gif --quiet --width 64 --height 48 --out dv"
RENDER_RD = "render --catalog cat.json --width 64 --height 48 --out rd"


def make_fixtures(fx: Path, log: Callable[[str], None]) -> None:
    _orig_make_fixtures(fx, log)
    if (fx / "done-shared").exists():
        return
    env = hs.child_env()

    def grl(*a: str) -> None:
        r = subprocess.run(hs.GRL + list(a), cwd=fx, capture_output=True, env=env)
        if r.returncode:
            raise SystemExit(f"fixture 'genesis-rl {' '.join(a)}' failed ({r.returncode}): "
                             f"{r.stderr.decode(errors='replace')[-2000:]}")

    rec = sorted((fx / "camp" / "records").glob("*.json"))[0]
    steps: list[tuple[str, Callable[[], object]]] = [
        ("bm", lambda: grl(*BM_ARGS.split(), "--out", "bm")),
        ("est", lambda: grl(*EST_ARGS.split(), "--out", "est")),
        ("zs", lambda: grl(*ZS_ARGS.split(), "--out", "zs")),
        ("ex", lambda: grl("export", "camp", "--out", "ex", "--quiet")),
        ("osc", lambda: grl("export", str(rec.relative_to(fx)), "--format", "openscenario", "--no-check", "--out", "osc", "--quiet")),
        ("dv", lambda: grl(*DRIVE_DV.split())),
        ("rd", lambda: grl(*RENDER_RD.split())),
        ("campr", lambda: shutil.copytree(fx / "camp", fx / "campr", symlinks=True)),  # holds the campaign's report.html
        ("w.pt", lambda: shutil.copy(hs.ROOT / "genesis_rl" / "sut" / "perception" / "weights" / "vehicle_detector.pt", fx / "w.pt")),
        ("hcamp", lambda: grl("evaluate", "--catalog", "hw.json", "--policies", "sunny", "--scenes", "1", "--steps", "20", "--system", "builtin",
                              "--out", "hcamp", "--quiet", "--no-report", "--no-counterfactual")),
    ]
    for name, make in steps:  # each kept once made: a failed fixture does not cost the others again
        if not (fx / name).exists():
            make()
            log(f"fixtures: {name}")
    (fx / "done-shared").write_text("ok")


# -- commands the cases share ------------------------------------------------------------------------------------
EVAL = hs.EVAL
EVAL_HW = hs.EVAL_HW
CAMP, RUN = hs.CAMP, hs.RUN
RESUME_CAMP = hs.RESUME_CAMP
BM, EST, ZS, HCAMP = cp("bm"), cp("est"), cp("zs"), cp("hcamp")
REPORT = "report camp --out rep.html"


def rebuilt(folder: str) -> tuple[str, ...]:
    """What report rewrites in the campaign it reads (as the harness allows for 'report camp')."""
    return tuple(f"{folder}/{n}" for n in ("summary.json", "episodes.csv", ".genesis-rl.manifest.json"))


def spec_env(key: str, value: Any) -> Setup:
    return edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "env", key], value))


def plan(steps: list[dict[str, Any]], pairs: list[tuple[str, str]], rename: tuple[str, str] = ("one", "two")) -> Setup:
    """A family-7 case: the steps to run and the files of the two results to compare."""
    return write("plan.json", json.dumps({"steps": steps, "pairs": pairs, "rename": rename}))


CMP_SCRIPT = r'''
import csv, glob, io, json, math, os, re, signal, subprocess, sys, time
plan = json.load(open("plan.json"))
GRL = [sys.executable, "-m", "genesis_rl"]
for step in plan["steps"]:
    p = subprocess.Popen(GRL + step["argv"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    sig = step.get("signal")
    if sig:
        t0 = time.time()
        while not glob.glob(sig["when"]) and p.poll() is None and time.time() - t0 < 300:
            time.sleep(0.05)
        time.sleep(sig.get("delay", 0.0))
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    out, err = p.communicate()
    sys.stdout.write(out.decode(errors="replace"))
    sys.stderr.write(err.decode(errors="replace"))
    if p.returncode not in step.get("ok", [0]):
        print(f"genesis-rl sweep: 'genesis-rl {' '.join(step['argv'])[:150]}' exited {p.returncode}", file=sys.stderr)
        sys.exit(4)
IGNORE = re.compile(r"(seconds|wall|elapsed|duration|started|finished|date|host|pid|version|argv|resum|^out$|folder|path|created|^time$|timestamp|per_s$|workers|executor|parallel)", re.I)
a_name, b_name = plan["rename"]
def norm(x):
    if isinstance(x, dict):
        return {k: norm(v) for k, v in x.items() if not IGNORE.search(k)}
    if isinstance(x, list):
        return [norm(v) for v in x]
    if isinstance(x, str):
        return x.replace(a_name, "OUT").replace(b_name, "OUT")
    return x
def first_diff(a, b, path):
    if type(a) != type(b):
        return f"{path}: {a!r} != {b!r}"
    if isinstance(a, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                return f"{path}/{k}: present in only one"
            d = first_diff(a[k], b[k], f"{path}/{k}")
            if d:
                return d
        return None
    if isinstance(a, list):
        if len(a) != len(b):
            return f"{path}: {len(a)} != {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            d = first_diff(x, y, f"{path}[{i}]")
            if d:
                return d
        return None
    if isinstance(a, float) and math.isnan(a) and math.isnan(b):
        return None
    return None if a == b else f"{path}: {a!r} != {b!r}"
def load(rel):
    text = open(rel, encoding="utf-8").read()
    if rel.endswith(".json"):
        return norm(json.loads(text))
    rows = list(csv.DictReader(io.StringIO(text)))
    return [norm(r) for r in rows]
pairs = []
for a, b in plan["pairs"]:
    if "*" in a:
        left, right = sorted(glob.glob(a)), sorted(glob.glob(b))
        if len(left) != len(right) or not left:
            print(f"genesis-rl sweep: {a} matches {len(left)} files, {b} {len(right)}", file=sys.stderr)
            sys.exit(3)
        pairs += list(zip(left, right))
    else:
        pairs.append((a, b))
for a, b in pairs:
    for rel in (a, b):
        if not os.path.isfile(rel):
            print(f"genesis-rl sweep: {rel} was not written", file=sys.stderr)
            sys.exit(3)
    d = first_diff(load(a), load(b), os.path.basename(a))
    if d:
        print(f"genesis-rl sweep: {a} and {b} differ: {d}"[:400], file=sys.stderr)
        sys.exit(3)
print(f"same: {len(pairs)} file pairs")
'''


#: family-7 comparisons left to --all: each runs a command two or three times (minutes on two shared cores)
LONG_7 = {"benchmark-parallel-episodes", "benchmark-sigterm-resume", "estimate-importance-workers-1-2", "estimate-sigterm-resume",
          "zoo-sweep-sigterm-resume", "reactivity-workers-1-2", "corners-twice-threads", "evaluate-twice", "evaluate-search-workers-1-2"}


def same(fam_id: str, what: str, steps: list[dict[str, Any]], pairs: list[tuple[str, str]], base: Setup | None, timeout: float = 900, rename: tuple[str, str] = ("one", "two"), **kw: Any) -> None:
    add(7, fam_id, what, [], setup=chain(base, plan(steps, pairs, rename), write("cmp.py", CMP_SCRIPT)), raw=[PY, "cmp.py"], expect=OK, timeout=timeout,
        core=fam_id not in LONG_7, **kw)


def _a(text: str) -> list[str]:
    return text.split()


# -- family 7 (a): the same floats in every mode ---------------------------------------------------------------
def family7() -> None:
    ev = EVAL_HW.replace("--policies sunny --scenes 1 --steps 5", "--policies sunny,random --scenes 2 --steps 40")
    same("evaluate-workers-1-2", "evaluate sunny,random on 2 highway scenes: --workers 1 against --workers 2 (pool); summary.json, episodes.csv, every episode",
         [{"argv": _a(f"{ev} --out one")}, {"argv": _a(f"{ev} --workers 2 --out two")}],
         [("one/summary.json", "two/summary.json"), ("one/episodes.csv", "two/episodes.csv"), ("one/episodes/*/*.json", "two/episodes/*/*.json")], cp("hw.json"))
    ev_b = EVAL.replace("--system blind", "--system builtin").replace("--scenes 1 --steps 5", "--scenes 2 --steps 30")
    same("evaluate-builtin-workers-1-2", "evaluate with the built-in detector (torch) on 2 urban scenes: --workers 1 against 2; the detector's floats",
         [{"argv": _a(f"{ev_b} --out one")}, {"argv": _a(f"{ev_b} --workers 2 --out two")}],
         [("one/summary.json", "two/summary.json"), ("one/episodes/*/*.json", "two/episodes/*/*.json")], cp("cat.json"))
    ev_s = EVAL_HW.replace("--policies sunny --scenes 1 --steps 5", "--policies cmaes --search-budget 2 --scenes 2 --steps 30")
    same("evaluate-search-workers-1-2", "evaluate a CMA-ES search (budget 2) on 2 scenes: --workers 1 against 2",
         [{"argv": _a(f"{ev_s} --out one")}, {"argv": _a(f"{ev_s} --workers 2 --out two")}],
         [("one/summary.json", "two/summary.json"), ("one/episodes/*/*.json", "two/episodes/*/*.json")], cp("hw.json"))
    ev_a = "evaluate --agent run --policies agent,random --catalog cat.json --scenes 2 --steps 20 --quiet --no-report --no-counterfactual"
    same("evaluate-agent-workers-1-2", "evaluate a trained PPO agent (torch) on 2 scenes: --workers 1 against 2",
         [{"argv": _a(f"{ev_a} --out one")}, {"argv": _a(f"{ev_a} --workers 2 --out two")}],
         [("one/summary.json", "two/summary.json"), ("one/episodes/*/*.json", "two/episodes/*/*.json")], chain(RUN, cp("cat.json")))
    same("evaluate-twice", "the same evaluate run twice (a control: one mode against itself)",
         [{"argv": _a(f"{ev} --out one")}, {"argv": _a(f"{ev} --out two")}],
         [("one/summary.json", "two/summary.json"), ("one/episodes.csv", "two/episodes.csv")], cp("hw.json"))
    same("evaluate-ray-local", "evaluate on Ray (one actor, its own local cluster) against in-process",
         [{"argv": _a(f"{ev} --out one")}, {"argv": _a(f"{ev} --executor ray --out two")}],
         [("one/summary.json", "two/summary.json"), ("one/episodes/*/*.json", "two/episodes/*/*.json")], cp("hw.json"), ray=True)
    ev3 = EVAL_HW.replace("--policies sunny --scenes 1 --steps 5", "--policies sunny,random --scenes 3 --steps 40")
    same("evaluate-sigterm-resume", "evaluate SIGTERMed after its first episode, then --resume, against uninterrupted",
         [{"argv": _a(f"{ev3} --out one"), "signal": {"when": "one/episodes/*/*.json", "delay": 0.1}, "ok": [0, 143, -15, 130]},
          {"argv": _a(f"{ev3} --out one --resume")}, {"argv": _a(f"{ev3} --out two")}],
         [("one/summary.json", "two/summary.json"), ("one/episodes.csv", "two/episodes.csv"), ("one/episodes/*/*.json", "two/episodes/*/*.json")], cp("hw.json"))
    bm = BM_ARGS
    bm_pairs = [("one/leaderboard.json", "two/leaderboard.json"), ("one/campaigns/*/*/summary.json", "two/campaigns/*/*/summary.json"),
                ("one/campaigns/*/*/episodes/*/*.json", "two/campaigns/*/*/episodes/*/*.json")]
    same("benchmark-workers-1-2", "a benchmark (oracle_highway, sunny+constant, 1 trial, 1 re-run): --workers 1 against 2; leaderboard.json",
         [{"argv": _a(f"{bm} --out one")}, {"argv": _a(f"{bm} --workers 2 --out two")}],
         bm_pairs, None)
    same("benchmark-parallel-episodes", "a benchmark with --workers 2 --parallel episodes against --parallel campaigns",
         [{"argv": _a(f"{bm} --workers 2 --parallel campaigns --out one")}, {"argv": _a(f"{bm} --workers 2 --parallel episodes --out two")}],
         bm_pairs, None)
    same("benchmark-sigterm-resume", "a benchmark SIGTERMed after its first campaign's episode, then --resume, against uninterrupted",
         [{"argv": _a(f"{bm} --out one"), "signal": {"when": "one/campaigns/*/*/episodes/*/*.json", "delay": 0.1}, "ok": [0, 143, -15, 130, 3]},
          {"argv": _a(f"{bm} --out one --resume")}, {"argv": _a(f"{bm} --out two")}],
         bm_pairs, None)
    est = EST_ARGS.replace("--episodes 4", "--episodes 6")
    same("estimate-workers-1-2", "estimate (crude, 6 episodes): --workers 1 against 2 (its help: results do not depend on it)",
         [{"argv": _a(f"{est} --out one")}, {"argv": _a(f"{est} --workers 2 --out two")}],
         [("one/estimate.json", "two/estimate.json"), ("one/episodes.csv", "two/episodes.csv")], None)
    esti = "estimate --member oracle_highway --method importance --episodes 8 --stages 2 --elite-min 1 --steps 20 --quiet"
    same("estimate-importance-workers-1-2", "estimate by importance sampling (2 stages): --workers 1 against 2",
         [{"argv": _a(f"{esti} --out one")}, {"argv": _a(f"{esti} --workers 2 --out two")}],
         [("one/estimate.json", "two/estimate.json"), ("one/episodes.csv", "two/episodes.csv")], None)
    same("estimate-sigterm-resume", "estimate SIGTERMed once episodes.csv appears, then --resume, against uninterrupted",
         [{"argv": _a(f"{est} --out one"), "signal": {"when": "one/episodes.csv", "delay": 0.0}, "ok": [0, 143, -15, 130, 3]},
          {"argv": _a(f"{est} --out one --resume")}, {"argv": _a(f"{est} --out two")}],
         [("one/estimate.json", "two/estimate.json"), ("one/episodes.csv", "two/episodes.csv")], None)
    zs = ZS_ARGS.replace("--scenes 1", "--scenes 2")
    same("zoo-sweep-workers-1-2", "zoo sweep (fog 0,60; 2 scenes): --workers 1 against 2; sweep.json",
         [{"argv": _a(f"{zs} --out one")}, {"argv": _a(f"{zs} --workers 2 --out two")}],
         [("one/sweep.json", "two/sweep.json")], None)
    same("zoo-sweep-sigterm-resume", "zoo sweep SIGTERMed after its first campaign's episode, then --resume, against uninterrupted",
         [{"argv": _a(f"{zs} --out one"), "signal": {"when": "one/campaigns/*/episodes/*/*.json", "delay": 0.1}, "ok": [0, 143, -15, 130, 3]},
          {"argv": _a(f"{zs} --out one --resume")}, {"argv": _a(f"{zs} --out two")}],
         [("one/sweep.json", "two/sweep.json")], None)
    rx = "reactivity --campaign camp --policy agent --scenes 2 --no-other-seeds --quiet"
    same("reactivity-workers-1-2", "reactivity of the fixture campaign's agent: --workers 1 against 2",
         [{"argv": _a(f"{rx} --out one.json")}, {"argv": _a(f"{rx} --workers 2 --out two.json")}],
         [("one.json", "two.json")], chain(CAMP, RUN, cp("hw.json")))
    dr = "drive --catalog cat.json --scene 0:2 --steps 20 --system builtin --no-gif --quiet --width 64 --height 48"
    same("drive-threads-1-2", "drive 2 scenes with the built-in detector: --threads 1 against 2; summary.json",
         [{"argv": _a(f"{dr} --out one")}, {"argv": _a(f"{dr} --threads 2 --out two")}],
         [("one/summary.json", "two/summary.json")], cp("cat.json"))
    co = "corners --config c.toml --scenes 1 --steps 3 --quiet"
    same("corners-twice-threads", "corners run with OMP_NUM_THREADS 1 (the harness's) twice: one mode against itself",
         [{"argv": _a(f"{co} --out one.json")}, {"argv": _a(f"{co} --out two.json")}],
         [("one.json", "two.json")], cp("tiny.toml", to="c.toml"))


# -- family 8 (b): an output onto a file an input names ---------------------------------------------------------
def family8() -> None:
    base = chain(CAMP, RUN, cp("hw.json"))
    # the fixture campaign names its catalog (hw.json) and its agent run (run/...)
    named = [("catalog", "hw.json"), ("agent-config", "run/config.toml"), ("agent-zip", "run/agent.zip"),
             ("agent-last-zip", "run/checkpoints/last.zip"), ("agent-run-json", "run/run.json"), ("agent-catalog", "run/catalog.json")]
    for name, rel in named:
        add(8, f"report-onto-{name}", f"report --out the campaign's {name} ({rel}) --force", f"report camp --out {rel} --force", setup=base)
        add(8, f"compare-onto-{name}", f"compare --json the campaign's {name} ({rel}) --force", f"compare a=camp:sunny b=camp:agent --json {rel} --force", setup=base)
    # files the campaign's env names: ODD, rulebook, weights in system_kwargs
    env_named = [("odd", "odd", "odd.toml", cp("odd.toml")), ("rulebook", "rulebook", "rules.toml", cp("rules.toml")),
                 ("weights", "system_kwargs", "w.pt", cp("w.pt"))]
    for name, key, rel, extra in env_named:
        value: Any = {"weights": rel} if key == "system_kwargs" else rel
        setup = chain(base, extra, spec_env(key, value))
        add(8, f"report-onto-env-{name}", f"report --out the {name} file the campaign's env names ({rel}) --force", f"report camp --out {rel} --force", setup=setup)
        add(8, f"compare-onto-env-{name}", f"compare --json the {name} file the campaign's env names ({rel}) --force", f"compare a=camp:sunny b=camp:agent --json {rel} --force", setup=setup)
        add(8, f"reactivity-onto-env-{name}", f"reactivity --out the {name} file the campaign's env names ({rel}) --force", f"reactivity --campaign camp --policy sunny --scenes 2 --no-other-seeds --quiet --out {rel} --force", setup=setup)
    add(8, "corners-onto-config-weights", "corners --out the weights its config's system_kwargs names --force", "corners --config c.toml --scenes 1 --steps 3 --quiet --out w.pt --force",
        setup=chain(cp("w.pt"), config("env", "system_kwargs", '{ weights = "w.pt" }')))
    add(8, "corners-onto-config-rulebook", "corners --out the rulebook its config names --force", "corners --config c.toml --scenes 1 --steps 3 --quiet --out rules.toml --force",
        setup=chain(cp("rules.toml"), config("env", "rulebook", '"rules.toml"')))
    add(8, "report-estimate-onto-estimate-json", "report --estimate est --out est/estimate.json --force", "report camp --estimate est --out est/estimate.json --force", setup=chain(base, EST))
    add(8, "report-onto-estimate-catalog", "report --estimate est --out est/catalog.json --force (the estimate's own catalog)", "report camp --estimate est --out est/catalog.json --force", setup=chain(base, EST))
    add(8, "estimate-nominal-inside-out", "estimate --nominal est/nominal.toml --out est --force (its input inside the folder it replaces)", f"{EST_ARGS} --nominal est/nominal.toml --out est --force",
        setup=chain(EST, write("est/nominal.toml", NOMINAL)), timeout=90)
    add(8, "estimate-weights-inside-out", "estimate --weights est/w.pt --out est --force", f"{EST_ARGS} --weights est/w.pt --out est --force", setup=chain(EST, cp("w.pt", to="est/w.pt")), timeout=90)
    add(8, "estimate-nominal-is-catalog", "estimate --nominal est/catalog.json (a file of ours by name) --out est --force", f"{EST_ARGS} --nominal est/catalog.json --out est --force", setup=EST, timeout=90)
    add(8, "harden-out-is-campaign", "harden hcamp --out hcamp --force", "harden hcamp --out hcamp --force --rounds 1 --test-scenes 1 --quiet", setup=HCAMP, timeout=90)
    add(8, "harden-out-inside-campaign", "harden hcamp --out hcamp/records --force", "harden hcamp --out hcamp/episodes --force --rounds 1 --test-scenes 1 --quiet", setup=HCAMP, timeout=90)
    add(8, "harden-out-is-agent-run", "harden camp --out run (the campaign's agent run) --force", "harden camp --out run --force --rounds 1 --test-scenes 1 --quiet", setup=base, timeout=90)
    add(8, "harden-out-holds-test-catalog", "harden --test-catalog h/t.json --out h --force", "harden hcamp --out h --test-catalog h/t.json --force --rounds 1 --test-scenes 1 --quiet",
        setup=chain(HCAMP, cp("hw.json", to="h/t.json")), timeout=90)
    add(8, "benchmark-out-is-estimate", "benchmark --estimate oracle_highway=est --out est --force", f"{BM_ARGS} --estimate oracle_highway=est --out est --force", setup=EST, timeout=90)
    add(8, "benchmark-out-inside-estimate", "benchmark --estimate oracle_highway=est --out est/bm", f"{BM_ARGS} --estimate oracle_highway=est --out est/bm", setup=EST, timeout=400, expect=EITHER)
    add(8, "train-config-names-catalog-in-out", "train --config c.toml (env.catalog = run/catalog.json) --out run --force", "train --config c.toml --out run --force --quiet",
        setup=chain(RUN, config("env", "catalog", '"run/catalog.json"')), timeout=120)
    add(8, "train-config-names-odd-in-out", "train --config c.toml (env.odd = run/config.toml, a file of ours) --out run --force", "train --config c.toml --out run --force --quiet",
        setup=chain(RUN, config("env", "odd", '"run/config.toml"')), timeout=120)


# -- family 9 (c): --force by the manifest -----------------------------------------------------------------------
def _append(rel: str, text: str = "\n") -> Setup:
    def setup(d: Path, fx: Path) -> None:
        with open(d / rel, "a") as fh:
            fh.write(text)
    return setup


def _edit_json_key(rel: str) -> Setup:
    return edit_json(rel, lambda c: c.update({"my_note": "checked by hand"}) if isinstance(c, dict) else None)


def stale_lock(folder: str) -> Setup:
    """The lock file a killed writer leaves beside its folder (nobody holds it)."""
    return write(f".{folder}.genesis-rl.lock", "999999\n")


def family9() -> None:
    F_EVAL = f"{EVAL_HW} --out camp --force"
    mf = "camp/.genesis-rl.manifest.json"
    tamper = [
        ("user-record", "a user's file named like a record (records/sunny_scene_0099.json)", write("camp/records/sunny_scene_0099.json", '{"mine": 1}'), "camp/records/sunny_scene_0099.json"),
        ("edited-summary", "the campaign's summary.json edited by hand", _edit_json_key("camp/summary.json"), "camp/summary.json"),
        ("edited-episodes-csv", "episodes.csv edited by hand (a row appended)", _append("camp/episodes.csv", "my,own,row\n"), "camp/episodes.csv"),
        ("user-frame", "a user's JPEG under frames/ named like a frame", write("camp/frames/agent/scene_0001/step_9999.jpg", b"\xff\xd8mine"), "camp/frames/agent/scene_0001/step_9999.jpg"),
        ("user-steps", "a user's Parquet under steps/ named like an episode's", write("camp/steps/agent/scene_0099.parquet", b"PAR1mine"), "camp/steps/agent/scene_0099.parquet"),
        ("edited-episode", "an episode JSON edited by hand", edit_json("camp/episodes/sunny/*.json", lambda e: e.update({"my_note": 1})), "@glob:camp/episodes/sunny/*.json"),
        ("user-damaged", "a user's file in damaged/ (a folder of ours)", write("camp/damaged/notes.txt", "mine"), "camp/damaged/notes.txt"),
        ("user-temp-name", "a user's file named like an atomic write's temporary (.summary.json.abcdefgh)", write("camp/.summary.json.abcdefgh", "mine"), "camp/.summary.json.abcdefgh"),
        ("edited-report-html", "a report.html of ours edited by hand", chain(cp("campr/report.html", to="camp/report.html"), _append("camp/report.html", "<p>my notes</p>")), "camp/report.html"),
        ("user-reactivity", "a user's reactivity_mine.json (named like ours)", write("camp/reactivity_mine.json", "{}"), "camp/reactivity_mine.json"),
    ]
    for name, what, setup, rel in tamper:
        rm, chk = _remember_glob(rel)
        add(9, f"campaign-{name}", f"evaluate --force onto a campaign holding {what}", F_EVAL, setup=chain(CAMP, cp("hw.json"), setup, rm),
            check=chk, names=(Path(rel).name.replace("*", "") if not rel.startswith("@") else "episodes/",), may_change=(mf,))
    # the manifest itself: damaged, missing, a link, nested, huge; with a hand-edited summary beside it
    edited = _edit_json_key("camp/summary.json")
    manifests = [
        ("manifest-truncated", "the manifest truncated to 20 bytes", hs.truncate(mf, 20)),
        ("manifest-missing", "the manifest deleted (as a folder of 0.30.0)", lambda d, fx: (d / mf).unlink()),
        ("manifest-link", "the manifest replaced by a symlink to a copy", lambda d, fx: (shutil.move(str(d / mf), str(d / "m.json")), os.symlink("../m.json", d / mf))),
        ("manifest-deep", "the manifest nested 100,000 deep", write(mf, deep_json(100_000))),
        ("manifest-wrong-schema", "the manifest's schema changed", edit_json(mf, lambda m: m.update({"schema": "x"}))),
        ("manifest-binary", "the manifest 64 KiB of binary", write(mf, hs.BIN * 16)),
    ]
    for name, what, tam in manifests:
        add(9, f"campaign-{name}", f"evaluate --force: {what}, and summary.json edited by hand", F_EVAL, setup=chain(CAMP, cp("hw.json"), edited, tam, remember("camp/summary.json")),
            check=kept("camp/summary.json"), names=("summary.json", "manifest"), may_change=(mf,))
    add(9, "campaign-stale-lock-edited", "a stale lock beside the campaign (a killed writer), then summary.json edited by hand; evaluate --force", F_EVAL,
        setup=chain(CAMP, cp("hw.json"), stale_lock("camp"), edited, remember("camp/summary.json")), check=kept("camp/summary.json"), names=("summary.json",), may_change=(mf, ".camp.genesis-rl.lock"))
    add(9, "campaign-stale-lock-user-record", "a stale lock beside the campaign, then a user's records/mine_scene_0001.json; evaluate --force", F_EVAL,
        setup=chain(CAMP, cp("hw.json"), stale_lock("camp"), write("camp/records/mine_scene_0001.json", "{}"), remember("camp/records/mine_scene_0001.json")),
        check=kept("camp/records/mine_scene_0001.json"), names=("mine_scene_0001.json",), may_change=(mf, ".camp.genesis-rl.lock"))
    add(9, "campaign-records-link", "the campaign's records/ replaced by a symlink to a user's folder; evaluate --force", F_EVAL,
        setup=chain(CAMP, cp("hw.json"), lambda d, fx: (shutil.move(str(d / "camp/records"), str(d / "myrecs")), os.symlink("../myrecs", d / "camp/records"))), names=("records",), may_change=(mf,))
    add(9, "campaign-summary-link", "the campaign's summary.json replaced by a symlink to a user's file; evaluate --force", F_EVAL,
        setup=chain(CAMP, cp("hw.json"), lambda d, fx: (shutil.move(str(d / "camp/summary.json"), str(d / "mine.json")), os.symlink("../mine.json", d / "camp/summary.json"))), names=("summary.json",), may_change=(mf,))
    add(9, "report-force-edited-report", "report --force over a report.html of ours edited by hand in the campaign", "report campr --force",
        setup=chain(cp("campr"), _append("campr/report.html", "<p>my notes</p>"), remember("campr/report.html")), check=kept("campr/report.html"), names=("report.html",),
        may_change=("campr/summary.json", "campr/episodes.csv", "campr/.genesis-rl.manifest.json"))
    add(9, "reactivity-force-edited", "reactivity --force over a reactivity_sunny.json of ours edited by hand", "reactivity --campaign camp --policy sunny --scenes 2 --no-other-seeds --quiet --force",
        setup=chain(CAMP, cp("hw.json"), write("camp/reactivity_sunny.json", '{"mine": 1}'), remember("camp/reactivity_sunny.json")), check=kept("camp/reactivity_sunny.json"), names=("reactivity_sunny.json",),
        may_change=(mf,), timeout=90)
    # a run
    F_TRAIN = "train --config tiny.toml --out run --force --quiet"
    rmf = "run/.genesis-rl.manifest.json"
    for name, what, setup, rel in [
        ("user-checkpoint", "a user's checkpoints/step_00000099.zip", write("run/checkpoints/step_00000099.zip", "mine"), "run/checkpoints/step_00000099.zip"),
        ("edited-last-json", "checkpoints/last.json edited by hand", _edit_json_key("run/checkpoints/last.json"), "run/checkpoints/last.json"),
        ("user-tb-events", "a user's tb/PPO_1/events.out.tfevents.mine", write("run/tb/PPO_1/events.out.tfevents.mine", "mine"), "run/tb/PPO_1/events.out.tfevents.mine"),
        ("edited-episodes-csv", "the run's episodes.csv edited by hand", _append("run/episodes.csv", "1,2,3\n"), "run/episodes.csv"),
        ("edited-train-result", "train_result.json edited by hand", _edit_json_key("run/train_result.json"), "run/train_result.json"),
    ]:
        add(9, f"run-{name}", f"train --force onto a run holding {what}", F_TRAIN, setup=chain(RUN, cp("tiny.toml"), setup, remember(rel)), check=kept(rel), names=(Path(rel).name,), may_change=(rmf,), timeout=120)
    # an export, a benchmark, a zoo sweep, an estimate
    for name, what, setup, rel in [
        ("user-image", "a user's image named like one (images/mine_scene0001_step0001.jpg)", write("ex/images/mine_scene0001_step0001.jpg", b"\xff\xd8mine"), "ex/images/mine_scene0001_step0001.jpg"),
        ("edited-data-yaml", "data.yaml edited by hand", _append("ex/data.yaml", "# mine\n"), "ex/data.yaml"),
        ("edited-metadata", "metadata.jsonl edited by hand", _append("ex/metadata.jsonl", '{"mine": 1}\n'), "ex/metadata.jsonl"),
    ]:
        add(9, f"export-{name}", f"export --force onto an export holding {what}", "export camp --out ex --force --quiet", setup=chain(CAMP, cp("ex"), setup, remember(rel)), check=kept(rel), names=(Path(rel).name,), may_change=("ex/.genesis-rl.manifest.json",), timeout=90)
    add(9, "osc-user-xosc", "export --format openscenario --force onto an export holding a user's scenarios/mine.xosc", "export @GLOB:camp/records/*.json@ --format openscenario --no-check --out osc --force --quiet",
        setup=chain(CAMP, cp("osc"), write("osc/scenarios/mine.xosc", "<mine/>"), remember("osc/scenarios/mine.xosc")), check=kept("osc/scenarios/mine.xosc"), names=("mine.xosc",), may_change=("osc/.genesis-rl.manifest.json",), timeout=90)
    F_BM = f"{BM_ARGS} --out bm --force"
    for name, what, setup, rel in [
        ("user-campaign-notes", "a user's notes in campaigns/ (a folder of ours)", write("bm/campaigns/notes.txt", "mine"), "bm/campaigns/notes.txt"),
        ("edited-leaderboard-html", "leaderboard.html edited by hand", _append("bm/leaderboard.html", "<p>mine</p>"), "bm/leaderboard.html"),
        ("user-reproduction", "a user's reproductions/x/mine.json", write("bm/reproductions/x/mine.json", "{}"), "bm/reproductions/x/mine.json"),
        ("edited-inner-summary", "a trial campaign's summary.json edited by hand", edit_json("bm/campaigns/*/*/summary.json", lambda c: c.update({"mine": 1})), "@glob:bm/campaigns/*/*/summary.json"),
    ]:
        rm2, chk = _remember_glob(rel)
        add(9, f"benchmark-{name}", f"benchmark --force onto a benchmark holding {what}", F_BM, setup=chain(BM, setup, rm2), check=chk, names=(Path(rel).name.replace("*", ""), "campaigns"), may_change=("bm/.genesis-rl.manifest.json",), timeout=120)
    add(9, "benchmark-manifest-missing-edited", "benchmark --force: its manifest deleted and leaderboard.html edited by hand", F_BM,
        setup=chain(BM, _append("bm/leaderboard.html", "<p>mine</p>"), lambda d, fx: (d / "bm/.genesis-rl.manifest.json").unlink(), remember("bm/leaderboard.html")), check=kept("bm/leaderboard.html"), names=("leaderboard.html", "manifest"),
        may_change=("bm/.genesis-rl.manifest.json",), timeout=120)
    for name, what, setup, rel in [
        ("user-campaign-file", "a user's file in campaigns/", write("zs/campaigns/mine.csv", "mine"), "zs/campaigns/mine.csv"),
        ("edited-sweep-json", "sweep.json edited by hand", _edit_json_key("zs/sweep.json"), "zs/sweep.json"),
    ]:
        add(9, f"sweep-{name}", f"zoo sweep --force onto a sweep holding {what}", f"{ZS_ARGS} --out zs --force", setup=chain(ZS, setup, remember(rel)), check=kept(rel), names=(Path(rel).name,), may_change=("zs/.genesis-rl.manifest.json",), timeout=120)
    for name, what, setup, rel in [
        ("edited-episodes-csv", "episodes.csv edited by hand", _append("est/episodes.csv", "mine\n"), "est/episodes.csv"),
        ("edited-estimate-json", "estimate.json edited by hand", _edit_json_key("est/estimate.json"), "est/estimate.json"),
    ]:
        add(9, f"estimate-{name}", f"estimate --force onto an estimate holding {what}", f"{EST_ARGS} --out est --force", setup=chain(EST, setup, remember(rel)), check=kept(rel), names=(Path(rel).name,), may_change=("est/.genesis-rl.manifest.json",), timeout=120)
    add(9, "drive-edited-summary", "drive --force onto a drive folder whose summary.json was edited by hand", f"{DRIVE_DV} --force",
        setup=chain(cp("cat.json"), cp("dv"), _edit_json_key("dv/summary.json"), remember("dv/summary.json")), check=kept("dv/summary.json"), names=("summary.json",), may_change=("dv/.genesis-rl.manifest.json",))
    add(9, "render-edited-boxes", "render --force onto a render folder whose boxes.json was edited by hand", f"{RENDER_RD} --force",
        setup=chain(cp("cat.json"), cp("rd"), _edit_json_key("rd/boxes.json"), remember("rd/boxes.json")), check=kept("rd/boxes.json"), names=("boxes.json",), may_change=("rd/.genesis-rl.manifest.json",))
    add(9, "harden-fake-folder-user-round", "harden --force onto a folder marked 'harden' holding a user's round_1/notes.txt and no manifest", "harden hcamp --out hd --force --rounds 1 --test-scenes 1 --quiet",
        setup=chain(HCAMP, write("hd/.genesis-rl.json", json.dumps({"schema": "genesis-rl/output-folder", "kind": "harden", "version": "0.30.0"})), write("hd/round_1/notes.txt", "mine"), remember("hd/round_1/notes.txt")),
        check=kept("hd/round_1/notes.txt"), names=("notes.txt", "round_1"), timeout=120)


CHECKS_DYNAMIC: dict[str, str] = {}


def _kept_dynamic(d: Path, out: str, err: str) -> tuple[str, str] | None:
    rel = CHECKS_DYNAMIC.get(str(d))
    return kept(rel)(d, out, err) if rel else None


def _remember_glob(rel: str) -> tuple[Setup, Callable[[Path, str, str], tuple[str, str] | None]]:
    if not rel.startswith("@glob:"):
        return remember(rel), kept(rel)
    pattern = rel[len("@glob:"):]

    def setup(d: Path, fx: Path) -> None:
        p = sorted(d.glob(pattern))[0]
        _SEEN[(str(d), str(p.relative_to(d)))] = p.read_bytes()
        CHECKS_DYNAMIC[str(d)] = str(p.relative_to(d))
    return setup, _kept_dynamic


# -- family 10 (d): escaping -------------------------------------------------------------------------------------
def _rename_policy(old: str, new: str, folder: str = "camp") -> Setup:
    def setup(d: Path, fx: Path) -> None:
        c = d / folder
        meta = json.loads((c / "campaign.json").read_text())
        meta["spec"]["policies"] = [new if p == old else p for p in meta["spec"]["policies"]]
        (c / "campaign.json").write_text(json.dumps(meta))
        for sub in ("episodes", "steps", "frames"):
            if (c / sub / old).is_dir():
                os.rename(c / sub / old, c / sub / new)
        for f in (c / "episodes" / new).iterdir():
            ep = json.loads(f.read_text())
            ep["policy"] = new
            f.write_text(json.dumps(ep))
        for f in (c / "records").glob(f"{old}_scene_*.json"):
            rec = json.loads(f.read_text())
            rec["policy"] = new
            f.write_text(json.dumps(rec))
    return setup


def _episode_field(key: str, value: Any, policy: str = "agent") -> Setup:
    def setup(d: Path, fx: Path) -> None:
        for f in sorted((d / "camp" / "episodes" / policy).glob("*.json"))[:1]:
            ep = json.loads(f.read_text())
            ep[key] = value
            f.write_text(json.dumps(ep))
    return setup


def _record_field(path: list[Any], value: Any) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        f = sorted((d / "camp" / "records").glob("*.json"))[0]
        rec = json.loads(f.read_text())
        set_path(rec, path, value)
        f.write_text(json.dumps(rec))
    return setup


HTML = ("rep.html", "camp/report*.html", "*.html", "*/*.html")
#: an estimate whose method and failure clusters are markup (the strings report.html and leaderboard.html quote)
HOSTILE_EST = edit_json("est/estimate.json", lambda e: (set_path(e, ["estimate", "method"], IMG), set_path(e, ["clusters"], [{"share": 0.5, "cluster": IMG}])))


def family10() -> None:
    R = "report camp --out rep.html --force"
    hm = (IMG, SCRIPT)
    add(10, "report-campaign-folder-name", "a campaign folder named '<img src=x onerror=alert(1)>'; report", ["report", IMG, "--out", "rep.html"],
        setup=cp("camp", to=IMG), check=raw_in(("rep.html",), IMG), expect=EITHER, may_change=rebuilt(IMG))
    add(10, "report-spec-system", "campaign.json's spec env.system is an <img> tag; report", R, setup=chain(CAMP, spec_env("system", IMG)), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-spec-agent", "campaign.json's spec agent is a </pre><script> string; report", R, setup=chain(CAMP, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "agent"], SCRIPT))), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-summary-map", "summary.json's map is an <img> tag; report", R, setup=chain(CAMP, edit_json("camp/summary.json", lambda s: s.update({"map": IMG}))), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-catalog-map", "campaign.json's map is an <img> tag; report", R, setup=chain(CAMP, edit_json("camp/campaign.json", lambda c: c.update({"map": IMG}))), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-package-version", "campaign.json's package_version is a </pre><script> string; report", R, setup=chain(CAMP, edit_json("camp/campaign.json", lambda c: c.update({"package_version": SCRIPT}))), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-policy-svg", "a policy renamed '<svg onload=alert(1)>' in campaign, episodes, steps, frames, records; report", R, setup=chain(CAMP, _rename_policy("sunny", SVG)), check=raw_in(HTML, SVG, *hm), expect=EITHER)
    add(10, "report-policy-quote-attr", "a policy renamed \"' onmouseover=alert(1) x='\" (an attribute breakout); report", R,
        setup=chain(CAMP, _rename_policy("sunny", "' onmouseover=alert(1) x='")), check=in_tag(HTML, "onmouseover=alert(1)"), expect=EITHER)
    add(10, "report-record-failure-mode", "a record's failure_mode is an <img> tag; report", R, setup=chain(CAMP, _record_field(["failure_mode"], IMG)), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-episode-record-name", "an episode's record file name holds an <img> tag; report", R, setup=chain(CAMP, _episode_field("record", f"records/{IMG}.json")), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-episode-strings", "every string of a failed episode (failure mode, nested ones) set to an <img> tag; report", R, setup=chain(CAMP, _all_strings(IMG)), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-odd-name", "the campaign's ODD (its env names it) has name and description <img> tags; report", R,
        setup=chain(CAMP, cp("odd.toml"), edit_text("odd.toml", lambda t: re.sub(r'(?m)^name = .*$', f'name = "{IMG}"\ndescription = "{SCRIPT}"', t, count=1)), spec_env("odd", "odd.toml")), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-knob-name", "campaign.json's spec env.knobs holds an <img> tag; report", R, setup=chain(CAMP, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "env", "knobs"], [IMG, "fog_density"]))), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-estimate-strings", "report --estimate EST whose estimate.json's method and failure cluster are <img> tags (the campaign set to its member's system and ODD)", "report camp --estimate est --out rep.html --force",
        setup=chain(CAMP, EST, HOSTILE_EST, cp("odd.toml", to="highway_day.toml"), spec_env("system", "oracle"), spec_env("odd", "highway_day.toml")), check=raw_in(HTML, *hm), expect=EITHER)
    add(10, "report-mathtext-failure-mode", "a record's failure_mode is mathtext '$\\undefinedcmd{x}$'; report (figures)", R, setup=chain(CAMP, _record_field(["failure_mode"], MATH), _episode_field("failure_mode", MATH)), expect=EITHER)
    add(10, "report-mathtext-campaign-name", "a campaign folder named '$\\undefinedcmd{x}$'; report", ["report", MATH, "--out", "rep.html"], setup=cp("camp", to=MATH), expect=EITHER, may_change=rebuilt(MATH))
    add(10, "leaderboard-estimate-strings", "benchmark --resume --estimate with estimate.json strings as <img> tags; leaderboard.html", f"{BM_ARGS} --out bm --resume --estimate oracle_highway=est",
        setup=chain(BM, EST, HOSTILE_EST), check=raw_in(("bm/leaderboard.html",), *hm), expect=EITHER, timeout=300)
    add(10, "leaderboard-spec-trials", "benchmark.json's spec trials is an <img> tag; benchmark --resume rebuilds the page", f"{BM_ARGS} --out bm --resume",
        setup=chain(BM, edit_json("bm/benchmark.json", lambda b: set_path(b, ["spec", "trials"], IMG))), check=raw_in(("bm/leaderboard.html",), *hm), timeout=120)
    # CSV cells
    for i, f in enumerate(FORMULAS):
        add(10, f"csv-failure-mode-{i}", f"an episode's failure_mode is {f!r}; report rewrites episodes.csv", R, setup=chain(CAMP, _episode_field("failure_mode", f, "sunny")),
            check=formula_cells(("camp/episodes.csv",)), expect=EITHER)
    add(10, "csv-policy-formula", "a policy renamed '-2+3' (a formula that looks like a number); report rewrites episodes.csv", R, setup=chain(CAMP, _rename_policy("sunny", "-2+3")), check=formula_cells(("camp/episodes.csv",)), expect=EITHER)
    add(10, "csv-every-string-formula", "every string field of an episode set to '=1+1'; report rewrites episodes.csv", R, setup=chain(CAMP, _all_strings("=1+1")), check=formula_cells(("camp/episodes.csv",)), expect=EITHER)
    add(10, "csv-resume-policy-formula", "a policy renamed '@SUM(1+1)'; evaluate --resume rewrites episodes.csv", RESUME_CAMP.replace("sunny,agent", "@SUM(1+1),agent"),
        setup=chain(CAMP, RUN, cp("hw.json"), _rename_policy("sunny", "@SUM(1+1)")), check=formula_cells(("camp/episodes.csv",)), expect=EITHER)
    add(10, "csv-estimate-resume", "an estimate's episodes.csv cluster cell set to '=1+1'; estimate --resume --episodes 6 rewrites it", f"{EST_ARGS.replace('--episodes 4', '--episodes 6')} --out est --resume",
        setup=chain(EST, edit_text("est/episodes.csv", _csv_set("cluster", "=1+1"))), check=formula_cells(("est/episodes.csv",)), expect=EITHER, timeout=120)
    # XML
    for name, path, value in [("failure-mode", ["failure_mode"], CTRL), ("policy-lt", ["policy"], "a</Act><x y='&"), ("system", ["system", "spec"], "blind\x0b"),
                              ("scene-map", ["scene", "map"], "urban\x01<x>")]:
        add(10, f"xosc-record-{name}", f"a record's {'.'.join(map(str, path))} holds {value!r}; export --format openscenario", "export @GLOB:camp/records/*.json@ --format openscenario --no-check --out x --quiet",
            setup=chain(CAMP, _record_field(path, value)), check=well_formed_xml(("x/**/*.xosc", "x/**/*.xodr")), expect=EITHER, timeout=90)
    add(10, "xosc-campaign-policy-ctrl", "a campaign policy renamed with control characters; export --format openscenario (whole campaign)", "export camp --format openscenario --no-check --out x --quiet",
        setup=chain(CAMP, _rename_policy("agent", CTRL)), check=well_formed_xml(("x/**/*.xosc",)), expect=EITHER, timeout=120)
    # the terminal
    add(10, "tty-catalog-path", "render --catalog a missing file whose name holds ESC sequences", ["render", "--catalog", f"{ESC}.json", "--out", "r"], check=terminal)
    add(10, "tty-compare-policy", "compare a policy renamed with ESC sequences (the table goes to stdout)", "compare a=camp:sunny b=camp:agent", setup=chain(CAMP, _rename_policy("sunny", ESC)),
        check=terminal, expect=EITHER)
    add(10, "tty-report-markdown", "report --markdown of a campaign whose policy holds ESC sequences", "report camp --markdown", setup=chain(CAMP, _rename_policy("sunny", ESC)), check=terminal, expect=EITHER)
    add(10, "tty-member-name", "benchmark --members with ESC sequences (echoed in the refusal)", ["benchmark", "--members", ESC, "--out", "b"], check=terminal)
    add(10, "tty-record-system", "replay a record whose system spec holds ESC sequences", hs.REPLAY, setup=chain(cp("rec.json"), edit_json("rec.json", lambda r: set_path(r, ["system", "spec"], ESC))), check=terminal)
    add(10, "tty-campaign-json-damaged", "report on a campaign whose campaign.json policies hold ESC sequences", REPORT, setup=chain(CAMP, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "policies"], [ESC]))), check=terminal, expect=EITHER)


def _set_strings(obj: Any, value: str) -> None:
    """Every string value below ``obj`` that is not a number's text, set to ``value`` (in place)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if isinstance(v, str):
                obj[k] = value
            else:
                _set_strings(v, value)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            if isinstance(v, str):
                obj[i] = value
            else:
                _set_strings(v, value)


def _all_strings(value: str) -> Setup:
    """Every string of the fixture's failed sunny episode (scene 5), nested ones too, but its policy and record."""
    def setup(d: Path, fx: Path) -> None:
        for f in sorted((d / "camp" / "episodes" / "sunny").glob("*.json")):
            ep = json.loads(f.read_text())
            if not ep.get("failure_mode"):
                continue
            keep = {k: ep[k] for k in ("policy", "record") if k in ep}
            _set_strings(ep, value)
            ep.update(keep)
            f.write_text(json.dumps(ep))
            return
    return setup


def _csv_set(column: str, value: str) -> Callable[[str], str]:
    """Set ``column`` of the first data row of a CSV text."""
    def fn(text: str) -> str:
        rows = list(csv.reader(io.StringIO(text)))
        rows[1][rows[0].index(column)] = value
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerows(rows)
        return buf.getvalue()
    return fn


# -- family 11 (e): sizes a file claims --------------------------------------------------------------------------
def _claim_size(rel: str, member: str, size: int) -> Setup:
    """Rewrite the central directory so that ``member`` claims ``size`` bytes (its data unchanged)."""
    def setup(d: Path, fx: Path) -> None:
        p = d / rel
        data = bytearray(p.read_bytes())
        name = member.encode()
        at = 0
        while (at := data.find(b"PK\x01\x02", at)) >= 0:
            n = int.from_bytes(data[at + 28:at + 30], "little")
            if bytes(data[at + 46:at + 46 + n]).endswith(name):
                data[at + 24:at + 28] = (min(size, 0xFFFFFFFE)).to_bytes(4, "little")
            at += 4
        p.write_bytes(bytes(data))
    return setup


def _bomb_member(rel: str, member: str, nbytes: int) -> Setup:
    """Replace ``member`` with ``nbytes`` of zeros, deflated (a ratio of about 1000x)."""
    def setup(d: Path, fx: Path) -> None:
        p = d / rel
        with zipfile.ZipFile(p) as z:
            members = {i.filename: z.read(i.filename) for i in z.infolist() if i.filename != member}
        with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as z:
            for name, data in members.items():
                z.writestr(name, data)
            with z.open(member, "w", force_zip64=True) as m:
                chunk = bytes(1 << 24)
                for _ in range(nbytes >> 24):
                    m.write(chunk)
    return setup


def _npy_header_claims(rel: str, member: str, shape: tuple[int, ...], dtype: str = "<f4") -> Setup:
    """Replace one array of an .npz by a .npy whose header claims ``shape`` (with a few bytes of data)."""
    def setup(d: Path, fx: Path) -> None:
        p = d / rel
        with zipfile.ZipFile(p) as z:
            members = {i.filename: z.read(i.filename) for i in z.infolist()}
        header = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode()
        header += b" " * (63 - (10 + len(header)) % 64) + b"\n"
        members[member] = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(64)
        with zipfile.ZipFile(p, "w") as z:
            for name, data in members.items():
                z.writestr(name, data)
    return setup


def _torch_bomb(rel: str, nbytes: int) -> Setup:
    """A torch checkpoint (a zip) whose one tensor's storage is ``nbytes`` of zeros, deflated."""
    def setup(d: Path, fx: Path) -> None:
        import torch

        buf = io.BytesIO()
        torch.save({"w": torch.zeros(4)}, buf)
        (d / rel).write_bytes(buf.getvalue())
        with zipfile.ZipFile(d / rel) as z:
            storage = next(n for n in z.namelist() if "/data/" in n and not n.endswith(".pkl"))
        _bomb_member(rel, storage, nbytes)(d, fx)
    return setup


def _parquet_rows(glob: str, factor: int) -> Setup:
    """A steps Parquet with its rows repeated ``factor`` times (the episode row's steps unchanged)."""
    def setup(d: Path, fx: Path) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        p = sorted(d.glob(glob))[0]
        t = pq.read_table(p)
        pq.write_table(pa.concat_tables([t] * factor), p)
    return setup


#: the steps of the fixture's failed episode (sunny, scene 5): its frames and record are what exports read
FAILED_STEPS = "camp/steps/sunny/scene_0005.parquet"


def family11() -> None:
    EA = hs.EVAL_AGENT
    add(11, "agent-data-claims-4gib", "agent.zip's 'data' member claims 4 GiB in the central directory; evaluate --agent", EA, setup=chain(RUN, cp("hw.json"), _claim_size("run/agent.zip", "data", 4 << 30)))
    add(11, "agent-policy-bomb", "agent.zip's policy.pth is 1 GiB of zeros deflated (1000x); evaluate --agent", EA, setup=chain(RUN, cp("hw.json"), _bomb_member("run/agent.zip", "policy.pth", 1 << 30)), timeout=90)
    add(11, "last-zip-bomb-fallback", "no agent.zip; checkpoints/last.zip's policy.pth a 1 GiB bomb; evaluate --agent falls back to it", EA,
        setup=chain(RUN, cp("hw.json"), lambda d, fx: (d / "run/agent.zip").unlink(), _bomb_member("run/checkpoints/last.zip", "policy.pth", 1 << 30)), timeout=90)
    add(11, "checkpoint-optimizer-bomb", "the checkpoint's policy.optimizer.pth a 1 GiB bomb; train --resume", hs.RESUME,
        setup=chain(RUN, _bomb_member("run/checkpoints/step_00000032.zip", "policy.optimizer.pth", 1 << 30)), timeout=90)
    add(11, "sac-variables-bomb", "a SAC agent's pytorch_variables.pth a 1 GiB bomb; evaluate --agent", EA.replace("--agent run", "--agent sacrun"),
        setup=chain(cp("sacrun"), cp("hw.json"), _bomb_member("sacrun/agent.zip", "pytorch_variables.pth", 1 << 30)), timeout=90)
    add(11, "weights-torch-bomb-drive", "--weights: a torch file whose storage is 1 GiB of zeros deflated; drive --system builtin", "drive --catalog cat.json --steps 2 --system builtin --weights w.pt --no-gif --quiet --width 64 --height 48 --out dv",
        setup=chain(cp("cat.json"), _torch_bomb("w.pt", 1 << 30)), names=("w.pt",), timeout=90)
    add(11, "weights-torch-bomb-estimate", "estimate --weights a torch file whose storage inflates to 1 GiB", f"{EST_ARGS} --weights w.pt --out e",
        setup=_torch_bomb("w.pt", 1 << 30), names=("w.pt",), timeout=300)
    add(11, "weights-claims-4gib", "--weights: a torch zip whose storage member claims 4 GiB; drive --system builtin", "drive --catalog cat.json --steps 2 --system builtin --weights w.pt --no-gif --quiet --width 64 --height 48 --out dv",
        setup=chain(cp("cat.json"), cp("w.pt"), lambda d, fx: _claim_size("w.pt", _first_storage(d / "w.pt"), 4 << 30)(d, fx)), names=("w.pt",), timeout=60)
    add(11, "replay-npz-shape-1e12", "the SAC run's replay buffer .npz: 'observations' header claims shape (10**12,); train --resume", "train --out sacrun --resume --steps 36 --quiet",
        setup=chain(cp("sacrun"), lambda d, fx: _npy_header_claims(str(sorted(d.glob("sacrun/checkpoints/*.replay.npz"))[0].relative_to(d)), "rewards.npy", (10**12,))(d, fx)), timeout=90)
    add(11, "replay-npz-shape-huge-2d", "the replay buffer's 'actions' header claims shape (10**7, 10**7); train --resume", "train --out sacrun --resume --steps 36 --quiet",
        setup=chain(cp("sacrun"), lambda d, fx: _npy_header_claims(str(sorted(d.glob("sacrun/checkpoints/*.replay.npz"))[0].relative_to(d)), "actions.npy", (10**7, 10**7))(d, fx)), timeout=90)
    add(11, "sb3-npz-shape-1e12", "the checkpoint's SB3 state .npz: 'last_episode_starts' claims shape (10**12,); train --resume", hs.RESUME,
        setup=chain(RUN, lambda d, fx: _npy_header_claims(str(sorted(d.glob("run/checkpoints/*.sb3.npz"))[-1].relative_to(d)), "last_episode_starts.npy", (10**12,), "|b1")(d, fx)), timeout=90)
    add(11, "sb3-npz-header-huge", "the checkpoint's SB3 state .npz: a header of 100 KB; train --resume", hs.RESUME,
        setup=chain(RUN, lambda d, fx: _npy_long_header(str(sorted(d.glob("run/checkpoints/*.sb3.npz"))[-1].relative_to(d)), "last_obs.npy")(d, fx)), timeout=90)
    add(11, "steps-parquet-3x-report", "a steps Parquet holding 3x its episode's steps (under the ceiling); report", REPORT, setup=chain(CAMP, _parquet_rows("camp/steps/agent/*.parquet", 3)), names=("parquet", "steps"))
    add(11, "steps-parquet-3x-export", "the failed episode's steps Parquet holding 3x its steps; export (yolo)", "export camp --out ex --quiet", setup=chain(CAMP, _parquet_rows(FAILED_STEPS, 3)), names=("parquet", "steps"), timeout=90)
    # the OpenSCENARIO export replays the failure's record and never reads a steps file: success is right
    add(11, "steps-parquet-3x-osc", "the failed episode's steps Parquet holding 3x its steps; export --format openscenario (reads records, not steps: exit 0)", "export camp --format openscenario --no-check --out x --quiet", setup=chain(CAMP, _parquet_rows(FAILED_STEPS, 3)), expect=(0,), timeout=300)
    add(11, "steps-parquet-1-row-harden", "a steps Parquet holding one row (its episode says 70); harden", "harden hcamp --out h --rounds 1 --test-scenes 1 --quiet",
        setup=chain(HCAMP, lambda d, fx: _parquet_head(d, "hcamp/steps/sunny/*.parquet", 1)), timeout=400)
    for name, rel, argv, base in [("benchmark-json", "bm/benchmark.json", f"{BM_ARGS} --out bm --resume", BM),
                                  ("sweep-json", "zs/sweep.json", f"{ZS_ARGS} --out zs --resume", ZS),
                                  ("estimate-json", "est/estimate.json", f"{EST_ARGS} --out est --resume", EST),
                                  ("leaderboard-json", "bm/leaderboard.json", f"{BM_ARGS} --out bm --resume", BM),
                                  ("bm-marker", "bm/.genesis-rl.json", f"{BM_ARGS} --out bm --force", BM),
                                  ("harden-json", "hd/harden.json", "harden hcamp --out hd --resume --rounds 1 --test-scenes 1 --quiet", chain(HCAMP, write("hd/.genesis-rl.json", json.dumps({"schema": "genesis-rl/output-folder", "kind": "harden", "version": "0.30.0"}))))]:
        add(11, f"deep-{name}", f"{rel} nested 100,000 deep; {argv.split()[0]} {'--force' if '--force' in argv else '--resume'}", argv, setup=chain(base, write(rel, deep_json(100_000))), timeout=120,
            expect=EITHER if name in ("leaderboard-json", "bm-marker") else REJECT)
    add(11, "estimate-nominal-deep", "estimate --nominal a TOML nested 100,000 deep", f"{EST_ARGS} --nominal n.toml --out e", setup=write("n.toml", deep_toml("x", 100_000)))
    add(11, "estimate-nominal-sparse-1gib", "estimate --nominal a 1 GiB sparse file", f"{EST_ARGS} --nominal n.toml --out e", setup=lambda d, fx: os.truncate(hs._touch(d / "n.toml"), 1 << 30))
    add(11, "harden-adversary-deep", "harden --adversary a TOML nested 100,000 deep", "harden hcamp --out h --adversary a.toml --rounds 1 --test-scenes 1 --quiet", setup=chain(HCAMP, write("a.toml", deep_toml("x", 100_000))), timeout=90)
    add(11, "harden-test-catalog-deep", "harden --test-catalog a JSON nested 100,000 deep", "harden hcamp --out h --test-catalog t.json --rounds 1 --test-scenes 1 --quiet", setup=chain(HCAMP, write("t.json", deep_json(100_000))), timeout=90)
    for name, argv, base in [("render-catalog", "render --catalog /dev/zero --width 64 --height 48 --out r", None),
                             ("drive-schedule", "drive --catalog cat.json --schedule /dev/zero --steps 5 --system blind --no-gif --quiet --width 64 --height 48 --out dv", cp("cat.json")),
                             ("drive-weights", "drive --catalog cat.json --steps 2 --system builtin --weights /dev/zero --no-gif --quiet --width 64 --height 48 --out dv", cp("cat.json")),
                             ("estimate-nominal", f"{EST_ARGS} --nominal /dev/zero --out e", None),
                             ("train-config", "train --config /dev/zero --out r --quiet", None),
                             ("harden-test-catalog", "harden hcamp --out h --test-catalog /dev/zero --rounds 1 --test-scenes 1 --quiet", HCAMP)]:
        add(11, f"dev-zero-{name}", f"{name.replace('-', ' --', 1)} /dev/zero (an endless file)", argv, setup=base, timeout=60)
    add(11, "record-weights-dev-zero", "a record's system_kwargs names weights /dev/zero; replay", hs.REPLAY,
        setup=chain(cp("rec.json"), edit_json("rec.json", lambda r: (set_path(r, ["system", "spec"], "builtin"), set_path(r, ["system", "kwargs"], {"weights": "/dev/zero"})))), timeout=60)
    add(11, "campaign-env-weights-dev-zero", "campaign.json's env system_kwargs names weights /dev/zero; reactivity", "reactivity --campaign camp --policy sunny --scenes 2 --no-other-seeds --quiet --out rx.json",
        setup=chain(CAMP, spec_env("system", "builtin"), spec_env("system_kwargs", {"weights": "/dev/zero"})), timeout=60)
    # one argument holds at most 128 KiB (Linux's MAX_ARG_STRLEN)
    add(11, "zoo-values-30k", "zoo sweep --values with 30,000 values", ["zoo", "sweep", "oracle_highway", "--knob", "fog_density", "--values", ",".join(["1"] * 30_000), "--scenes", "1", "--out", "z"], timeout=60)
    add(11, "zoo-truth-onsets-30k", "zoo truth --onsets with 30,000 values", ["zoo", "truth", "stall_braking", "--onsets", ",".join(["1"] * 30_000), "--out", "t.json"], timeout=60)
    add(11, "benchmark-members-5k", "benchmark --members with 5,000 names", ["benchmark", "--members", ",".join(["oracle_highway"] * 5_000), "--policies", "sunny", "--out", "b"], timeout=60)


def _first_storage(p: Path) -> str:
    with zipfile.ZipFile(p) as z:
        return next(n for n in z.namelist() if "/data/" in n and not n.endswith(".pkl"))


def _npy_long_header(rel: str, member: str) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        p = d / rel
        with zipfile.ZipFile(p) as z:
            members = {i.filename: z.read(i.filename) for i in z.infolist()}
        header = ("{'descr': '<f4', 'fortran_order': False, 'shape': (1,), " + "'x': 0, " * 12_000 + "}").encode()
        header += b" " * (63 - (12 + len(header)) % 64) + b"\n"
        members[member] = b"\x93NUMPY\x02\x00" + len(header).to_bytes(4, "little") + header + bytes(8)
        with zipfile.ZipFile(p, "w") as z:
            for name, data in members.items():
                z.writestr(name, data)
    return setup


def _parquet_head(d: Path, glob: str, n: int) -> None:
    import pyarrow.parquet as pq

    p = sorted(d.glob(glob))[0]
    pq.write_table(pq.read_table(p).slice(0, n), p)


# -- family 12 (f): resume and the import gate ------------------------------------------------------------------
BAD_MODULES = [("main-module", "genesis_rl.__main__:X"), ("entry", "genesis_rl.commands.entry:main"), ("os-system", "os:system"),
               ("builtins-exec", "builtins:exec"), ("cli-main", "genesis_rl.commands.cli:main"), ("remove-tree", "genesis_rl.core.files.io_utils:remove_tree"),
               ("old-cli-path", "genesis_rl.cli:main"), ("module-type", "genesis_rl.sut:__class__"), ("function-in-layer", "genesis_rl.sut.system.protocol:load_system"),
               ("abstract-policy", "genesis_rl.adversaries.base:WeatherPolicy"), ("abstract-backend", "genesis_rl.sim.backends:Backend"), ("antigravity", "antigravity:x"),
               ("relative", ".evil:Sys"), ("empty-module", ":Sys")]


def family12() -> None:
    for name, spec in BAD_MODULES:
        add(12, f"record-system-{name}", f"a record's system spec is {spec!r}; replay", hs.REPLAY, setup=chain(cp("rec.json"), edit_json("rec.json", lambda r, s=spec: set_path(r, ["system", "spec"], s))))
    for name, spec in [("entry", "genesis_rl.commands.entry:main"), ("os-system", "os:system"), ("abstract-backend", "genesis_rl.sim.backends:Backend"), ("module-type", "genesis_rl.sim:__class__")]:
        add(12, f"record-backend-{name}", f"a record's backend is {spec!r}; replay", hs.REPLAY, setup=chain(cp("rec.json"), edit_json("rec.json", lambda r, s=spec: set_path(r, ["backend"], s))))
        add(12, f"catalog-backend-{name}", f"a catalog's backend is {spec!r}; render", hs.RENDER, setup=chain(cp("cat.json"), edit_json("cat.json", lambda c, s=spec: set_path(c, ["backend"], s))))
    for name, spec in [("entry", "genesis_rl.commands.entry:main"), ("abstract-policy", "genesis_rl.adversaries.base:WeatherPolicy"), ("cli-main", "genesis_rl.commands.cli:main")]:
        add(12, f"campaign-policy-{name}", f"campaign.json's spec policy {spec!r}; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), edit_json("camp/campaign.json", lambda c, s=spec: set_path(c, ["spec", "policies"], ["sunny", s]))))
    for name, spec in [("entry", "genesis_rl.commands.entry:main"), ("os-system", "os:system"), ("abstract-rule", "genesis_rl.loop.rules.rulebook:Rule")]:
        add(12, f"rulebook-rule-{name}", f"a rulebook rule named {spec!r}; evaluate --config", "evaluate --config rcfg.toml --catalog cat.json --policies sunny --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out e",
            setup=chain(cp("rcfg.toml", "cat.json"), write("rules.toml", f'[[rules]]\nname = "{spec}"\npriority = 1\n')))
    for name, mods in [("main", '["genesis_rl.__main__"]'), ("entry", '["genesis_rl.commands.entry"]'), ("antigravity", '["antigravity"]'), ("this", '["this"]')]:
        add(12, f"run-config-plugins-{name}", f"the run's config.toml names env.plugins = {mods}; evaluate --agent", hs.EVAL_AGENT,
            setup=chain(RUN, cp("hw.json"), edit_text("run/config.toml", lambda t, m=mods: toml_set(t, "env", "plugins", m))), check=lambda d, o, e: ("code-exec", "'this' printed the Zen of Python") if "Beautiful is better" in o + e else None)
    add(12, "record-system-kwargs-unknown", "a record's system kwargs hold an unknown key; replay", hs.REPLAY, setup=chain(cp("rec.json"), edit_json("rec.json", lambda r: set_path(r, ["system", "kwargs"], {"nonsense": 1}))))
    add(12, "record-system-kwargs-list", "a record's system kwargs is a list; replay", hs.REPLAY, setup=chain(cp("rec.json"), edit_json("rec.json", lambda r: set_path(r, ["system", "kwargs"], [1, 2]))))
    # resume with edited specs
    R_BM = f"{BM_ARGS} --out bm --resume"
    add(12, "benchmark-spec-trials", "benchmark.json's spec trials edited (1 -> 3); benchmark --resume", R_BM, setup=chain(BM, edit_json("bm/benchmark.json", lambda b: set_path(b, ["spec", "trials"], 3))), names=("trials",), timeout=120)
    add(12, "benchmark-spec-policies", "benchmark.json's spec policies edited (constant -> random); benchmark --resume", R_BM, setup=chain(BM, edit_json("bm/benchmark.json", lambda b: set_path(b, ["spec", "policies"], ["sunny", "random"]))), names=("policies",), timeout=120)
    add(12, "benchmark-spec-missing", "benchmark.json has no spec; benchmark --resume", R_BM, setup=chain(BM, edit_json("bm/benchmark.json", lambda b: b.pop("spec", None))), timeout=120)
    add(12, "benchmark-trial-steps", "a kept trial's campaign.json spec steps edited (20 -> 30); benchmark --resume", R_BM, setup=chain(BM, edit_json("bm/campaigns/*/*/campaign.json", lambda c: set_path(c, ["spec", "steps"], 30))), names=("campaign.json", "steps"), timeout=120)
    add(12, "benchmark-trial-system-entry", "a kept trial's campaign.json env.system = 'genesis_rl.commands.entry:main'; benchmark --resume", R_BM,
        setup=chain(BM, edit_json("bm/campaigns/*/*/campaign.json", lambda c: set_path(c, ["spec", "env", "system"], "genesis_rl.commands.entry:main"))), timeout=120)
    add(12, "benchmark-trial-seeds", "a kept trial's campaign.json episode seeds edited; benchmark --resume", R_BM, setup=chain(BM, edit_json("bm/campaigns/*/*/campaign.json", lambda c: set_path(c, ["scenes", 0, 1], 4242))), names=("campaign.json", "seed", "scenes"), timeout=120)
    add(12, "benchmark-reproduction-edited", "a kept reproduction JSON edited (its failures set to 0); benchmark --resume", R_BM,
        setup=chain(BM, lambda d, fx: [edit_json(str(p.relative_to(d)), lambda r: _set_numbers(r, 0))(d, fx) for p in sorted(d.glob("bm/reproductions/*/*.json"))[:1]]), expect=EITHER, timeout=120)
    R_ZS = f"{ZS_ARGS} --out zs --resume"
    add(12, "sweep-spec-values", "sweep.json's spec values edited; zoo sweep --resume", R_ZS, setup=chain(ZS, edit_json("zs/sweep.json", lambda s: _edit_spec(s, "values", [0, 10]))), names=("values", "sweep.json"), timeout=120)
    add(12, "sweep-campaign-steps", "a kept sweep campaign's spec steps edited; zoo sweep --resume", R_ZS, setup=chain(ZS, edit_json("zs/campaigns/*/campaign.json", lambda c: set_path(c, ["spec", "steps"], 30))), names=("campaign.json", "steps"), timeout=120)
    add(12, "sweep-campaign-policy-entry", "a kept sweep campaign's policy 'genesis_rl.commands.entry:main'; zoo sweep --resume", R_ZS,
        setup=chain(ZS, edit_json("zs/campaigns/*/campaign.json", lambda c: set_path(c, ["spec", "policies"], ["genesis_rl.commands.entry:main"]))), timeout=120)
    R_EST = f"{EST_ARGS} --out est --resume"
    for key, value in [("episodes", 5), ("seed", 9), ("method", "importance"), ("member", "latency_braking"), ("steps", 30)]:
        add(12, f"estimate-spec-{key}", f"estimate.json's spec {key} edited; estimate --resume" + (" (crude may change --episodes: either is right)" if key == "episodes" else ""), R_EST,
            setup=chain(EST, edit_json("est/estimate.json", lambda e, k=key, v=value: _edit_spec(e, k, v))), names=(key, "estimate.json"), timeout=120, expect=EITHER if key == "episodes" else REJECT)
    add(12, "estimate-catalog-edited", "the estimate's catalog.json edited (a speed); estimate --resume", R_EST, setup=chain(EST, edit_text("est/catalog.json", lambda t: re.sub(r'("speed": ?)[-0-9.e]+', r"\g<1>3.0", t, count=1))), names=("catalog.json",), timeout=120)
    add(12, "estimate-episodes-csv-edited", "the estimate's episodes.csv edited (a row's numbers changed); estimate --resume", R_EST, setup=chain(EST, edit_text("est/episodes.csv", _csv_change_number())), names=("episodes.csv",), expect=EITHER, timeout=120)
    add(12, "estimate-episodes-csv-int-damaged", "the estimate's episodes.csv episode_seed cell 'x'; estimate --resume --episodes 6", f"{EST_ARGS.replace('--episodes 4', '--episodes 6')} --out est --resume", setup=chain(EST, edit_text("est/episodes.csv", _csv_set("episode_seed", "x"))), names=("episodes.csv",), timeout=120)
    add(12, "estimate-episodes-csv-extra", "the estimate's episodes.csv holds a duplicate row; estimate --resume", R_EST, setup=chain(EST, edit_text("est/episodes.csv", lambda t: t + t.splitlines()[1] + "\n")), names=("episodes.csv",), expect=EITHER, timeout=120,
        check=_episodes_counted("est/estimate.json", 4))
    R_HD = "harden hcamp --out hd --resume --rounds 1 --test-scenes 1 --quiet"
    fake = chain(HCAMP, write("hd/.genesis-rl.json", json.dumps({"schema": "genesis-rl/output-folder", "kind": "harden", "version": "0.30.0"})))
    add(12, "harden-spec-retrain-entry", "a harden folder whose harden.json spec names retrain 'genesis_rl.commands.entry:main'; harden --resume", R_HD,
        setup=chain(fake, write("hd/harden.json", json.dumps({"spec": {"campaign": "hcamp", "rounds": 1, "test_scenes": 1, "retrain": "genesis_rl.commands.entry:main"}}))), timeout=120)
    add(12, "harden-spec-rounds", "a harden folder whose harden.json spec rounds = 5; harden --resume --rounds 1", R_HD,
        setup=chain(fake, write("hd/harden.json", json.dumps({"spec": {"campaign": "hcamp", "rounds": 5, "test_scenes": 1, "retrain": "builtin"}}))), names=("rounds", "harden.json", "was started with"), timeout=120)  # the first setting that differs is named
    add(12, "harden-spec-list", "a harden folder whose harden.json is a list; harden --resume", R_HD, setup=chain(fake, write("hd/harden.json", "[]")), timeout=120)


def _episodes_counted(rel: str, n: int) -> Callable[[Path, str, str], tuple[str, str] | None]:
    def check(d: Path, out: str, err: str) -> tuple[str, str] | None:
        try:
            got = json.loads((d / rel).read_text())["estimate"]["episodes"]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return None if got == n else ("wrong-exit", f"{rel} counts {got} episodes of {n} (a duplicated row counted twice)")
    return check


def _set_numbers(obj: Any, value: int) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and "fail" in k:
                obj[k] = value
            else:
                _set_numbers(v, value)
    elif isinstance(obj, list):
        for v in obj:
            _set_numbers(v, value)


def _edit_spec(data: Any, key: str, value: Any) -> None:
    spec = data.get("spec") if isinstance(data, dict) else None
    if isinstance(spec, dict):
        spec[key] = value


def _csv_change_number() -> Callable[[str], str]:
    """The first data row's first start variable (a float that sets the episode) moved by 1.5."""
    def fn(text: str) -> str:
        rows = list(csv.reader(io.StringIO(text)))
        i = next(i for i, h in enumerate(rows[0]) if h.startswith("start_"))
        rows[1][i] = repr(float(rows[1][i]) + 1.5)
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerows(rows)
        return buf.getvalue()
    return fn


# -- family 13 (g): smaller ----------------------------------------------------------------------------------------
def _full(cmd: str) -> list[str]:
    return ["bash", "-c", f"exec {PY} -m genesis_rl {cmd} > /dev/full"]


def family13() -> None:
    # --out x/ for one-file outputs
    for name, argv, base in [("reactivity", "reactivity --campaign camp --policy sunny --scenes 2 --no-other-seeds --quiet --out rx/", CAMP),
                             ("corners", "corners --config c.toml --scenes 1 --steps 3 --quiet --out co/", cp("tiny.toml", to="c.toml")),
                             ("compare", "compare a=camp:sunny b=camp:agent --json cj/", CAMP),
                             ("report", "report camp --out rp/", CAMP),
                             ("zoo-truth", "zoo truth stall_braking --tuning 1 --held-out 1 --onsets 2 --out zt/ --quiet", None),
                             ("scenes", "scenes --count 1 --out sc/ --quiet", None),
                             ("map", "map export --out mp/", None)]:
        add(13, f"out-slash-{name}", f"{name} --out NEWDIR/ (a one-file output named as a folder)", argv, setup=base, absent=(argv.split("--out ")[1].split()[0].rstrip("/") if "--out " in argv else argv.split("--json ")[1].split()[0].rstrip("/"),), timeout=90)
    # output that cannot be written: /dev/full
    for name, cmd in [("benchmark-help", "benchmark --help"), ("zoo-sweep-help", "zoo sweep --help"), ("estimate-help", "estimate --help"), ("harden-help", "harden --help"),
                      ("speed-help", "speed --help"), ("bench-alias-help", "bench --help"), ("version", "--version"), ("zoo-list", "zoo list"), ("benchmark-list", "benchmark --list"),
                      ("report-markdown", "report camp --markdown"), ("compare", "compare a=camp:sunny b=camp:agent"), ("scenes-stdout", "scenes --count 1 --out - --quiet"),
                      ("map-stdout", "map export --out -"), ("models-list", "models list")]:
        add(13, f"dev-full-{name}", f"genesis-rl {cmd} with stdout a full device (/dev/full)", [], raw=_full(cmd), setup=CAMP if "camp" in cmd else None, timeout=60)
    # signals at odd moments, then --resume
    for name, argv, when, then in [
        ("benchmark-in-trial", f"{BM_ARGS} --out b", "b/campaigns/*/*/episodes/*/*.json", f"{BM_ARGS} --out b --resume"),
        ("benchmark-in-reruns", f"{BM_ARGS} --out b", "b/reproductions", f"{BM_ARGS} --out b --resume"),
        ("estimate-in-episodes", f"{EST_ARGS} --out e", "e/episodes.csv", f"{EST_ARGS} --out e --resume"),
        ("sweep-second-value", f"{ZS_ARGS} --out z", "z/campaigns/*/summary.json", f"{ZS_ARGS} --out z --resume"),
        ("export-in-images", "export camp --out x --quiet", "x/images/*.jpg", "export camp --out x --force --quiet"),
        ("report-writing", "report camp --out rep.html", ".rep.html.*", "report camp --out rep.html --force"),
    ]:
        add(13, f"sigterm-{name}", f"SIGTERM {name.replace('-', ' ')}, then {then.split('--out')[0].split()[0]} {'--resume' if '--resume' in then else '--force'}", argv,
            setup=CAMP if "camp" in argv else None, signal_when=when, signal_at=0.05, signal_num=signal.SIGTERM, expect=(0, 130, 143, 3), then=then.split(), timeout=180,
            may_change=("camp/summary.json", "camp/episodes.csv", "camp/.genesis-rl.manifest.json") if "camp" in argv else ())
    # --smoke with matrix flags
    for flag in ("--trials 3", "--scenes 2", "--seed 1", "--steps 10", "--start fixed", "--reruns 0", "--members oracle_highway", "--policies sunny", "--agent latency_braking=run", "--search-budget 2"):
        add(13, f"smoke-{flag.split()[0][2:]}", f"benchmark --smoke {flag}", f"benchmark --smoke {flag} --out b --quiet", setup=RUN if "run" in flag else None, names=(flag.split()[0],), timeout=60)
    # odd numbers on the new commands' count and fraction flags
    odd = [("benchmark-trials-0", f"{BM_ARGS.replace('--trials 1', '--trials 0')} --out b"), ("benchmark-trials-neg", f"{BM_ARGS.replace('--trials 1', '--trials -1')} --out b"),
           ("benchmark-trials-1e12", f"{BM_ARGS.replace('--trials 1', '--trials 1000000000000')} --out b"), ("benchmark-scenes-0", f"{BM_ARGS.replace('--scenes 1', '--scenes 0')} --out b"),
           ("benchmark-steps-0", f"{BM_ARGS.replace('--steps 20', '--steps 0')} --out b"), ("benchmark-steps-neg", f"{BM_ARGS.replace('--steps 20', '--steps -5')} --out b"),
           ("benchmark-reruns-neg", f"{BM_ARGS.replace('--reruns 1', '--reruns -1')} --out b"), ("benchmark-reruns-1e12", f"{BM_ARGS.replace('--reruns 1', '--reruns 1000000000000')} --out b"),
           ("benchmark-search-budget-0", f"{BM_ARGS} --search-budget 0 --out b"),
           ("estimate-episodes-0", f"{EST_ARGS.replace('--episodes 4', '--episodes 0')} --out e"), ("estimate-episodes-1e12", f"{EST_ARGS.replace('--episodes 4', '--episodes 1000000000000')} --out e"),
           ("estimate-stages-0", f"{EST_ARGS.replace('crude', 'importance')} --stages 0 --out e"), ("estimate-stages-1e9", f"{EST_ARGS.replace('crude', 'importance')} --stages 1000000000 --out e"),
           ("estimate-pilot-1.5", f"{EST_ARGS.replace('crude', 'importance')} --pilot 1.5 --out e"), ("estimate-pilot-nan", f"{EST_ARGS.replace('crude', 'importance')} --pilot nan --out e"),
           ("estimate-defensive-neg", f"{EST_ARGS.replace('crude', 'importance')} --defensive -0.1 --out e"), ("estimate-defensive-nan", f"{EST_ARGS.replace('crude', 'importance')} --defensive nan --out e"),
           ("estimate-elite-0", f"{EST_ARGS.replace('crude', 'importance')} --elite 0 --out e"), ("estimate-elite-2", f"{EST_ARGS.replace('crude', 'importance')} --elite 2 --out e"),
           ("estimate-elite-min-neg", f"{EST_ARGS.replace('crude', 'importance')} --elite-min -1 --out e"), ("estimate-smoothing-nan", f"{EST_ARGS.replace('crude', 'importance')} --smoothing nan --out e"),
           ("estimate-smoothing-inf", f"{EST_ARGS.replace('crude', 'importance')} --smoothing inf --out e"), ("estimate-steps-0", f"{EST_ARGS.replace('--steps 20', '--steps 0')} --out e"),
           ("estimate-tilt-unknown", f"{EST_ARGS.replace('crude', 'importance').replace('--episodes 4', '--episodes 20')} --tilt nonsense,, --stages 2 --out e"),
           ("sweep-scenes-0", f"{ZS_ARGS.replace('--scenes 1', '--scenes 0')} --out z"), ("sweep-scenes-1e12", f"{ZS_ARGS.replace('--scenes 1', '--scenes 1000000000000')} --out z"),
           ("sweep-steps-neg", f"{ZS_ARGS.replace('--steps 20', '--steps -1')} --out z"), ("sweep-values-nan", f"{ZS_ARGS.replace('0,60', 'nan')} --out z"),
           ("sweep-values-inf", f"{ZS_ARGS.replace('0,60', '0,inf')} --out z"), ("sweep-values-1e308", f"{ZS_ARGS.replace('0,60', '1e308')} --out z"),
           ("sweep-values-empty-item", f"{ZS_ARGS.replace('0,60', '0,,60')} --out z"), ("sweep-values-out-of-range", f"{ZS_ARGS.replace('0,60', '-50,1000')} --out z"),
           ("sweep-hold-nan", f"{ZS_ARGS} --hold lead_decel=nan --out z"), ("sweep-hold-unknown", f"{ZS_ARGS} --hold nonsense=1 --out z"), ("sweep-knob-unknown", f"{ZS_ARGS.replace('fog_density', 'nonsense')} --out z"),
           ("truth-tuning-0", "zoo truth stall_braking --tuning 0 --out t.json --quiet"), ("truth-held-out-neg", "zoo truth stall_braking --held-out -1 --out t.json --quiet"),
           ("truth-onsets-nan", "zoo truth stall_braking --onsets nan --out t.json --quiet"), ("truth-onsets-neg", "zoo truth stall_braking --onsets -1 --out t.json --quiet"),
           ("harden-rounds-0", "harden hcamp --out h --rounds 0 --quiet"), ("harden-rounds-1e12", "harden hcamp --out h --rounds 1000000000000 --quiet"),
           ("harden-test-scenes-0", "harden hcamp --out h --test-scenes 0 --quiet"), ("harden-epochs-0", "harden hcamp --out h --epochs 0 --quiet"),
           ("harden-lr-nan", "harden hcamp --out h --lr nan --quiet"), ("harden-distill-inf", "harden hcamp --out h --distill inf --quiet"),
           ("harden-tolerance-nan", "harden hcamp --out h --tolerance nan --quiet"), ("harden-near-miss-neg", "harden hcamp --out h --near-miss-ttc -1 --quiet"),
           ("harden-clear-frames-1e12", "harden hcamp --out h --clear-frames 1000000000000 --quiet"), ("harden-estimate-episodes-neg", "harden hcamp --out h --estimate-episodes -1 --quiet"),
           ("export-osc-version", "export @GLOB:camp/records/*.json@ --format openscenario --osc-version 9.9 --no-check --out x --quiet"),
           ("replay-world-seed-huge", f"{hs.REPLAY} --world-seed 100000000000000000000000000000"), ("compare-seed-neg", "compare a=camp:sunny b=camp:agent --seed -1")]
    for name, argv in odd:
        base = HCAMP if "hcamp" in argv else CAMP if "camp" in argv else cp("rec.json") if "rec.json" in argv else None
        flag = next((a for a in argv.split() if a.startswith("--") and a not in ("--out", "--quiet", "--method", "--member", "--knob", "--values", "--episodes", "--steps", "--scenes", "--policies", "--members", "--trials", "--reruns", "--format", "--no-check", "--no-gif")), None)
        flag = {"odd-benchmark-trials": "--trials", "odd-benchmark-scenes": "--scenes", "odd-benchmark-steps": "--steps", "odd-benchmark-reruns": "--reruns", "odd-estimate-episodes": "--episodes",
                "odd-estimate-steps": "--steps", "odd-sweep-scenes": "--scenes", "odd-sweep-steps": "--steps", "odd-sweep-values": "--values"}.get("odd-" + "-".join(name.split("-")[:2]), flag)
        add(13, f"odd-{name}", f"{argv.split(' --out')[0][:90]}", argv, setup=base, timeout=60, expect=EITHER if name in ("compare-seed-neg", "benchmark-reruns-neg") else REJECT,
            names=(flag.lstrip("-"), flag.lstrip("-").replace("-", "_")) if flag else ())
    # odd bytes in paths and names
    add(13, "path-newline-out", "evaluate --out a folder name holding a newline", [*EVAL_HW.split(), "--out", "a\nb"], setup=cp("hw.json"), expect=EITHER)
    add(13, "path-non-utf8-scenes", "scenes --out a name with a byte that is not UTF-8 (\\xff)", ["scenes", "--count", "1", "--out", "\udcff.json", "--quiet"], expect=EITHER)
    add(13, "path-non-utf8-report", "report --out a name with a byte that is not UTF-8", ["report", "camp", "--out", "\udcff.html"], setup=CAMP, expect=EITHER)
    add(13, "path-non-utf8-benchmark", "benchmark --out a name with a byte that is not UTF-8", [*BM_ARGS.split(), "--out", "b\udcff"], expect=EITHER, timeout=120)
    add(13, "path-non-utf8-campaign", "report on a campaign folder whose name is not UTF-8", ["report", "c\udcff", "--out", "rep.html"], setup=cp("camp", to="c\udcff"), expect=EITHER, may_change=rebuilt("c\udcff"))
    add(13, "path-non-utf8-export", "export --out a folder name that is not UTF-8", ["export", "camp", "--out", "x\udcff", "--quiet"], setup=CAMP, expect=EITHER, timeout=90)
    add(13, "path-long-estimate", "estimate --out a 300-character folder name", [*EST_ARGS.split(), "--out", "e" * 300], names=("e" * 20, "long"))
    add(13, "path-long-benchmark", "benchmark --out a 300-character folder name", [*BM_ARGS.split(), "--out", "b" * 300], names=("b" * 20, "long"))
    # no folder can be named with a NUL, so only campaign.json says it
    add(13, "name-nul-policy", "a campaign policy name holding NUL (in campaign.json); report", REPORT, setup=chain(CAMP, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "policies"], ["sun\x00ny" if p == "sunny" else p for p in c["spec"]["policies"]]))), expect=EITHER)
    add(13, "name-nul-catalog-path", "campaign.json's spec catalog path holds NUL; reactivity", "reactivity --campaign camp --policy sunny --scenes 2 --no-other-seeds --quiet --out rx.json",
        setup=chain(CAMP, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "catalog"], "hw.json\x00x"))))
    add(13, "name-nul-system-kwargs", "campaign.json's env system_kwargs weights path holds NUL; compare --json", "compare a=camp:sunny b=camp:agent --json c.json",
        setup=chain(CAMP, spec_env("system_kwargs", {"weights": "w\x00.pt"})), expect=EITHER)
    add(13, "name-rtl-member", "benchmark --members with a right-to-left override", ["benchmark", "--members", "oracle\u202ehighway", "--out", "b"], names=("members", "oracle"))
    add(13, "name-unicode-out", "evaluate --out a name with combining marks and emoji", [*EVAL_HW.split(), "--out", "e\u0301\U0001F600"], setup=cp("hw.json"), expect=OK)


# -- the sweep ------------------------------------------------------------------------------------------------------
def build_cases() -> None:
    if hs.CASES:
        return
    family8()  # the long comparisons of family 7 last: a sweep cut short still has the rest
    family9()
    family10()
    family11()
    family12()
    family13()
    family7()
    ids = [c.id for c in hs.CASES]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise SystemExit(f"duplicate case ids: {dup}")


def markdown(rows: list[dict[str, Any]]) -> str:
    text = _orig_markdown(rows)
    # the cases' own payloads (ESC, BEL, NUL, bytes that are not UTF-8) are shown as escapes, not written raw
    text = text.encode("utf-8", "backslashreplace").decode("utf-8")
    text = re.sub(r"[\x00-\x08\x0b-\x1f\x7f]", lambda m: f"\\x{ord(m.group(0)):02x}", text)
    return text.replace("# Hostile-input sweep (issue 38)", "# Hostile-input sweep of the shared files (after 0.30.0)", 1).replace(
        "Made by `tests/hostile/sweep_files.py`; one row a case. Outcomes: pass, code-exec, data-loss, abort, traceback, timeout, wrong-exit (see the script's docstring). Cases marked * are the issue's own examples; the others are new.",
        "Made by `tests/hostile/sweep_shared.py` (the harness of `tests/hostile/sweep_files.py`); one row a case. Outcomes: pass, code-exec, data-loss, abort, traceback, timeout, wrong-exit, unescaped (see the scripts' docstrings). Every case is new.", 1)


_orig_markdown = hs.markdown
hs.FAMILIES = FAMILIES
hs.OUTCOMES = OUTCOMES
hs._run = _run
hs.run_case = run_case
hs.make_fixtures = make_fixtures
hs.build_cases = build_cases
hs.markdown = markdown
CASES = hs.CASES


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if "--out" not in args and "--list" not in args and "--render" not in args:
        args += ["--out", "sweep_shared.json"]
    return int(hs.main(args))


if __name__ == "__main__":
    raise SystemExit(main())
