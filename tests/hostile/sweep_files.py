"""Hostile-input sweep for issue 38 ("Trust nothing a file says"), organised by the issue's six families.

    PYTHONPATH=$PWD .venv/bin/python tests/hostile/sweep_files.py --out sweep.json [--family N] [--jobs 2]
        [--markdown docs/reliability/sweep.md] [--work DIR] [--limit N] [--ids ID,ID] [--all] [--list]

The default set (368 cases, 341 of them new relative to the issue's examples) takes about 10 minutes on two idle
cores once the fixes refuse early; ``--all`` adds the rest of each value grid (478 cases, 451 new). ``--work DIR`` keeps
the fixtures and each case's folder for inspection; ``--render JSON --markdown MD`` re-renders a table. The exit
status is 1 when any case fails.

It builds tiny fixtures once (a scene catalog per map, a tiny PPO run and a tiny SAC run with system blind, a
tiny campaign with records, an ODD, a rulebook, a config, a schedule CSV), then runs each case as a
subprocess ``python -m genesis_rl ...`` in a folder of its own holding copies of the fixtures it needs, mutated
the way a careless user, a colleague sharing a run folder or a damaged disk would. Every case is judged by the
same oracle, strictest finding first:

* ``code-exec``: a crafted pickle or a module named by a file created the marker file ``PWNED``;
* ``data-loss``: a file, link, FIFO or device that was in the case folder before the command is gone or
  changed (outputs the case asked to replace are listed in ``may_change``);
* ``abort``: killed by a signal, exit 134/139, or "Fatal Python error"/"terminate called" on stderr;
* ``traceback``: "Traceback (most recent call last)" on stdout or stderr;
* ``timeout``: still running after the case's limit (the whole process group is killed);
* ``wrong-exit``: an exit status the case does not allow (2 with a message for rejected input, 0 where
  the input is valid), or temporaries/locks left after an interrupt, or a file the case forbids (``-``);
* ``pass`` otherwise.

Only loopback addresses are used: CARLA and Ray addresses point at listeners this script starts on 127.0.0.1
(a closed port, an HTTP-like server, a silent one, one sending garbage, an echo server). Writes its JSON to
``--out`` and a Markdown table grouped by family to ``--markdown``. Seeded: the same code gives the same cases.
"""

# ruff: noqa: E501 - the cases are a table, one a line
from __future__ import annotations

import argparse
import base64
import io
import json
import os
import pickle
import random
import re
import resource
import shutil
import signal
import socket
import socketserver
import stat
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the shared builders
from builders import tiny_run  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]  # the repository (this file is tests/hostile/sweep_files.py)
PY = sys.executable
GRL = [PY, "-m", "genesis_rl"]
FAMILIES = {
    1: "an output lands on its own input",
    2: "opening a shared run runs its code",
    3: "files trusted, numbers unchecked",
    4: "tracebacks and aborts (parsing, CARLA, interrupts)",
    5: "no bound on work",
    6: "Ray cluster, addresses and workers",
}
OUTCOMES = ("pass", "code-exec", "data-loss", "abort", "traceback", "timeout", "wrong-exit")
REJECT, OK, EITHER = (2,), (0,), (0, 2)
MARKER = "PWNED"  # what a payload creates, in the case folder
MEMORY_LIMIT = 8 * 2**30  # address space of one command (not Ray's): a runaway allocation fails, the box lives

Setup = Callable[[Path, Path], object]  # (case folder, fixtures folder); what it returns is ignored


@dataclass
class Case:
    id: str
    family: int
    what: str
    argv: list[str]  # after "genesis-rl"; @GLOB:pattern@ and @PORT_name@ are filled in when it runs
    setup: Setup | None = None
    expect: tuple[int, ...] = REJECT
    may_change: tuple[str, ...] = ()  # paths (relative to the case folder) the command may replace
    absent: tuple[str, ...] = ()  # paths that must not exist afterwards (a file named '-')
    timeout: float = 60.0
    signal_at: float | None = None  # send SIGINT/SIGTERM (signal_num) to the process group this many s after
    signal_when: str = ""  # ... a path matching this glob (relative to the case folder) appears ("": the start)
    signal_num: int = signal.SIGINT
    then: list[str] | None = None  # a follow-up command (e.g. --resume) that must exit 0
    raw: list[str] | None = None  # run this command instead of genesis-rl (the harness's own test)
    from_issue: bool = False  # an example the issue text gives (not counted as new)
    ray: bool = False  # runs Ray: no memory limit, its own RAY_TMPDIR, its leftover processes ended by pid
    names: tuple[str, ...] = ()  # a refusal (exit 2) must name one of these (the file or field at fault)
    warns: tuple[str, ...] = ()  # a success (exit 0) must say one of these on stderr (a warning)
    core: bool = True  # in the default sweep (~10 min on 2 cores); the rest of a value grid runs with --all


CASES: list[Case] = []


def case(family: int, cid: str, what: str, argv: str | list[str], **kw: Any) -> None:
    args = argv.split() if isinstance(argv, str) else argv
    if "--resume" in args and "--out" in args:  # resuming continues the folder: its own files change
        kw["may_change"] = (*kw.get("may_change", ()), args[args.index("--out") + 1])
    if args[:2] == ["report", "camp"] and family != 1:  # report rebuilds a damaged summary from the episodes
        kw["may_change"] = (*kw.get("may_change", ()), "camp/summary.json", "camp/episodes.csv")
    CASES.append(Case(f"f{family}-{cid}", family, what, args, **kw))


# -- setup helpers ---------------------------------------------------------------------------------------------
def chain(*steps: Setup | None) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        for s in steps:
            if s is not None:
                s(d, fx)
    return setup


def cp(*names: str, to: str | None = None) -> Setup:
    """Copy fixtures into the case folder (``to``: under this name or folder)."""
    def setup(d: Path, fx: Path) -> None:
        for name in names:
            src = fx / name
            dst = d / (to if to and len(names) == 1 and not to.endswith("/") else (to or "") + name)
            dst.parent.mkdir(parents=True, exist_ok=True)
            if src.is_dir():
                shutil.copytree(src, dst, symlinks=True)
            else:
                shutil.copy2(src, dst)
    return setup


def write(rel: str, data: bytes | str) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data.encode() if isinstance(data, str) else data)
    return setup


def edit_text(rel: str, fn: Callable[[str], str]) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        p = sorted(d.glob(rel))[0]
        p.write_text(fn(p.read_text()))
    return setup


def edit_json(rel: str, fn: Callable[[Any], Any]) -> Setup:
    """Apply ``fn`` to a JSON file's parsed content in place (``fn`` may mutate and return None)."""
    def setup(d: Path, fx: Path) -> None:
        p = sorted(d.glob(rel))[0]
        data = json.loads(p.read_text())
        out = fn(data)
        p.write_text(json.dumps(data if out is None else out))  # allow_nan: NaN, Infinity as Python writes them
    return setup


def truncate(rel: str, keep: int) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        p = sorted(d.glob(rel))[0]
        p.write_bytes(p.read_bytes()[:keep])
    return setup


def symlink(rel: str, target: str) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        (d / rel).parent.mkdir(parents=True, exist_ok=True)
        os.symlink(target, d / rel)
    return setup


def fifo(rel: str) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        os.mkfifo(d / rel)
    return setup


def devnull(rel: str) -> Setup:
    """A character device like /dev/null, made in the case folder (so a command that replaces it harms nothing)."""
    def setup(d: Path, fx: Path) -> None:
        try:
            os.mknod(d / rel, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        except OSError:  # not root: a FIFO stands in for the special file
            os.mkfifo(d / rel)
    return setup


_LOCKS: dict[Path, list[int]] = {}  # case folder -> lock file descriptors this harness holds while it runs


def hold_lock(rel: str) -> Setup:
    """Hold ``rel`` locked (flock, as genesis-rl's output lock) while the command runs: a run still training."""
    import fcntl

    def setup(d: Path, fx: Path) -> None:
        fd = os.open(d / rel, os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(fd, f"{os.getpid()}\n".encode())
        _LOCKS.setdefault(d, []).append(fd)
    return setup


def hardlink(rel: str, target: str) -> Setup:
    def setup(d: Path, fx: Path) -> None:
        os.link(d / target, d / rel)
    return setup


def set_path(obj: Any, path: Sequence[Any], value: Any) -> None:
    for key in path[:-1]:
        obj = obj[key]
    obj[path[-1]] = value


class _Payload:
    """Unpickling this calls ``open(marker, "w")``: the marker file appears if anything unpickles it."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        return (open, (self.marker, "w"))


def payload(d: Path) -> bytes:
    return pickle.dumps(_Payload(str(d / MARKER)), protocol=4)


def torch_payload(d: Path) -> bytes:
    import torch  # the harness runs under the package's environment

    buf = io.BytesIO()
    torch.save(_Payload(str(d / MARKER)), buf)
    return buf.getvalue()


def zip_member(rel: str, member: str, make: Callable[[Path, bytes], bytes]) -> Setup:
    """Rewrite one member of a zip (an SB3 agent or checkpoint) with ``make(case folder, old bytes)``."""
    def setup(d: Path, fx: Path) -> None:
        p = d / rel
        with zipfile.ZipFile(p) as z:
            members = {i.filename: z.read(i.filename) for i in z.infolist()}
        members[member] = make(d, members[member])
        with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as z:
            for name, data in members.items():
                z.writestr(name, data)
    return setup


def serialized(entry: str) -> Callable[[Path, bytes], bytes]:
    """SB3's ``data``: replace the cloudpickled ``:serialized:`` of ``entry`` with the payload."""
    def make(d: Path, old: bytes) -> bytes:
        data = json.loads(old)
        item = data.get(entry)
        if not isinstance(item, dict):
            item = {":type:": "<class 'function'>"}
            data[entry] = item
        item[":serialized:"] = base64.b64encode(payload(d)).decode()
        return json.dumps(data).encode()
    return make


def evil_module(name: str = "evil") -> Setup:
    """A module in the case folder (the command's working directory, so importable) that creates the marker
    when imported, with classes of every plug-in kind's name."""
    def setup(d: Path, fx: Path) -> None:
        (d / f"{name}.py").write_text(
            f"open({str(d / MARKER)!r}, 'w').close()\n"
            "class Sys:\n    pass\nclass Backend:\n    pass\nclass Rule:\n    pass\nclass Pol:\n    pass\n")
    return setup


def deep_json(depth: int) -> str:
    return "[" * depth + "]" * depth


def deep_toml(key: str, depth: int) -> str:
    return f"{key} = " + "[" * depth + "]" * depth + "\n"


BIN = bytes(range(256)) * 16
LATIN1 = "[env]\nmap = \"urban\"\n# caf\xe9\n".encode("latin-1")


# -- fixtures --------------------------------------------------------------------------------------------------
TINY = tiny_run(train={"total_timesteps": 32})
TINY64 = TINY.replace("total_timesteps = 32", "total_timesteps = 96")
SAC = """[env]
map = "urban"
scenes = 2
system = "blind"
episode_steps = 10
camera_width = 64
camera_height = 48
obs_width = 36
obs_height = 36

[sac]
buffer_size = 64
learning_starts = 8
batch_size = 8
net_arch = [16, 16]

[train]
algorithm = "sac"
total_timesteps = 24
checkpoint_every = 12
seed = 3
torch_threads = 1
"""
SCHEDULE = "step,fog_density,precipitation\n" + "".join(f"{i},{10 * i},{5 * i}\n" for i in range(5))


def make_fixtures(fx: Path, log: Callable[[str], None]) -> None:
    if (fx / "done").exists():
        return
    if fx.exists():
        shutil.rmtree(fx)
    fx.mkdir(parents=True)
    env = child_env()

    def grl(*a: str) -> None:
        r = subprocess.run(GRL + list(a), cwd=fx, capture_output=True, env=env)
        if r.returncode:
            raise SystemExit(f"fixture 'genesis-rl {' '.join(a)}' failed ({r.returncode}): "
                             f"{r.stderr.decode(errors='replace')[-2000:]}")

    t0 = time.time()
    (fx / "tiny.toml").write_text(TINY)
    (fx / "tiny64.toml").write_text(TINY64)
    (fx / "sac.toml").write_text(SAC)
    (fx / "sched.csv").write_text(SCHEDULE)
    shutil.copy(ROOT / "configs" / "odd" / "highway_day.toml", fx / "odd.toml")
    shutil.copy(ROOT / "configs" / "rulebook.toml", fx / "rules.toml")
    (fx / "rcfg.toml").write_text(TINY.replace("[ppo]", "rulebook = \"rules.toml\"\n\n[ppo]"))
    grl("scenes", "--count", "2", "--out", "cat.json", "--quiet")
    grl("scenes", "--map", "highway", "--count", "12", "--out", "hw.json", "--quiet")
    log(f"fixtures: catalogs ({time.time() - t0:.0f} s)")
    grl("train", "--config", "tiny.toml", "--out", "run", "--quiet")
    grl("train", "--config", "sac.toml", "--out", "sacrun", "--quiet")
    log(f"fixtures: runs ({time.time() - t0:.0f} s)")
    # the blind system never sees a vehicle: one of these highway scenes ends in a collision (frames are kept,
    # so export has work), another in a proximity failure; each failure writes a record
    grl("evaluate", "--agent", "run", "--catalog", "hw.json", "--policies", "sunny,agent", "--scenes", "3",
        "--seed", "1", "--steps", "70", "--system", "blind", "--out", "camp", "--quiet", "--records", "failures",
        "--no-counterfactual")
    records = sorted((fx / "camp" / "records").glob("*.json"))
    if not records or not (fx / "camp" / "frames").is_dir():
        raise SystemExit("fixture campaign wrote no record or no failure frames")
    shutil.copy(records[0], fx / "rec.json")
    log(f"fixtures: campaign ({time.time() - t0:.0f} s)")
    (fx / "done").write_text("ok")


# -- loopback listeners ----------------------------------------------------------------------------------------
class _Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True


def _handler(kind: str) -> type[socketserver.BaseRequestHandler]:
    class H(socketserver.BaseRequestHandler):
        def handle(self) -> None:
            s = self.request
            s.settimeout(120)
            try:
                if kind == "http":
                    s.recv(4096)
                    s.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                elif kind == "garbage":
                    s.sendall(random.Random(7).randbytes(65536))
                elif kind == "echo":
                    while data := s.recv(65536):
                        s.sendall(data)
                else:  # silent: hold the connection, say nothing
                    while s.recv(65536):
                        pass
            except OSError:
                pass
    return H


def start_listeners() -> dict[str, int]:
    ports: dict[str, int] = {}
    for kind in ("http", "garbage", "echo", "silent"):
        srv = _Server(("127.0.0.1", 0), _handler(kind))
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        ports[kind] = srv.server_address[1]
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    ports["closed"] = s.getsockname()[1]
    s.close()  # nothing listens there now
    return ports


# -- running ---------------------------------------------------------------------------------------------------
def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("GENESIS_RL_") and k != "RAY_ADDRESS"}
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update({"PYTHONUNBUFFERED": "1", "PYTHONHASHSEED": "0", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"})
    env.update(extra or {})
    return env


def entry_state(p: Path) -> str:
    """What a path is, to compare before and after: a link's target, a special file's kind, a file's bytes."""
    st = os.lstat(p)
    if stat.S_ISLNK(st.st_mode):
        return "link:" + os.readlink(p)
    if stat.S_ISFIFO(st.st_mode):
        return "fifo"
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):
        return f"dev:{os.major(st.st_rdev)},{os.minor(st.st_rdev)}"
    if stat.S_ISREG(st.st_mode):
        import hashlib

        h = hashlib.sha256()
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        return h.hexdigest()
    return "other"


def snapshot(root: Path) -> dict[str, str]:
    out: dict[str, str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in filenames + [n for n in dirnames if os.path.islink(os.path.join(dirpath, n))]:
            p = Path(dirpath) / name
            try:
                out[str(p.relative_to(root))] = entry_state(p)
            except OSError:
                out[str(p.relative_to(root))] = "unreadable"
    return out


TEMP_RE = re.compile(r"(\.partial$|\.lock$|\.zip\.\w+\.zip$|^\..+\.\w{6,}\.\w+$|\.tmp$)")


def leftovers(root: Path) -> list[str]:
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            if TEMP_RE.search(name) and not name.startswith((".genesis-rl.json", ".genesis-rl.manifest.json")):
                found.append(str((Path(dirpath) / name).relative_to(root)))
    return found


def fill(arg: str, d: Path, ports: dict[str, int]) -> str:
    for k, v in ports.items():
        arg = arg.replace(f"@PORT_{k}@", str(v))

    def glob(m: re.Match[str]) -> str:
        hits = sorted(d.glob(m.group(1)))
        return str(hits[0].relative_to(d)) if hits else m.group(1)
    return re.sub(r"@GLOB:([^@]+)@", glob, arg)


def _limits(ray: bool) -> Callable[[], None]:
    def pre() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)  # a background parent leaves SIGINT ignored
        if not ray:
            resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    return pre


def _run(cmd: list[str], d: Path, env: dict[str, str], c: Case) -> tuple[int | None, str, str, float]:
    """(exit status or None on timeout, stdout, stderr, seconds)."""
    t0 = time.time()
    p = subprocess.Popen(cmd, cwd=d, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env=env, start_new_session=True, preexec_fn=_limits(c.ray))
    stop = threading.Event()
    sent: list[float] = []

    def watch() -> None:  # polls for the file whose appearance marks the moment to interrupt
        while c.signal_when and not stop.is_set() and not any(d.glob(c.signal_when)):
            time.sleep(0.02)
        if not stop.wait(c.signal_at or 0.0) and p.poll() is None:
            sent.append(time.time() - t0)
            _killpg(p.pid, c.signal_num)

    watcher = threading.Thread(target=watch, daemon=True)
    if c.signal_at is not None:
        watcher.start()
    try:
        out, err = p.communicate(timeout=c.timeout)
        code: int | None = p.returncode
    except subprocess.TimeoutExpired:
        _killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        code = None
    finally:
        stop.set()
    note = "" if c.signal_at is None else f"\n(sweep: signal sent at {sent[0]:.1f} s)" if sent else \
        "\n(sweep: the command ended before the moment to signal it)"
    return code, out.decode(errors="replace"), err.decode(errors="replace") + note, time.time() - t0


def _killpg(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)
    except ProcessLookupError:
        pass


def _end_ray(tag: str) -> None:
    """End the Ray processes one case started (their command lines name its RAY_TMPDIR), by pid."""
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            if tag.encode() in (proc / "cmdline").read_bytes() or tag.encode() in (proc / "environ").read_bytes():
                os.kill(int(proc.name), signal.SIGKILL)
        except (OSError, ProcessLookupError):
            pass


def message(stderr: str, limit: int | None = 300) -> str:
    """The command's own last message line (else the last line), cut to ``limit`` characters."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip() and "%|" not in ln]
    errs = [ln for ln in lines if ln.startswith("genesis-rl")]
    return (errs[-1] if errs else lines[-1] if lines else "")[:limit]


def judge(c: Case, d: Path, code: int | None, out: str, err: str, lost: list[str],
          problems: Sequence[str] = ()) -> tuple[str, str]:
    """(outcome, detail): the strictest finding first."""
    both = out + "\n" + err
    if (d / MARKER).exists():
        return "code-exec", f"the marker {MARKER} was created"
    if lost:
        return "data-loss", "changed or gone: " + ", ".join(lost[:4])
    interrupted = c.signal_at is not None and code == -c.signal_num  # SIGTERM's default: end by the signal
    if code is not None and not interrupted and (code < 0 or code in (134, 139)) or "Fatal Python error" in both \
            or "terminate called" in both:
        return "abort", f"exit {code}"
    if "Traceback (most recent call last)" in both:
        tb = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(" ")]
        return "traceback", (tb[-1] if tb else "traceback on stdout")[:300]
    if code is None:
        return "timeout", f"still running after {c.timeout:.0f} s"
    if code not in c.expect and not interrupted:
        return "wrong-exit", f"exit {code}, expected {' or '.join(map(str, c.expect))}"
    if code == 2 and not message(err):
        return "wrong-exit", "exit 2 without a message"
    if code == 2 and c.names and not any(n.lower() in message(err, None).lower() for n in c.names):
        return "wrong-exit", f"refused, but not naming {' or '.join(c.names)}"
    if code == 0 and c.warns and not any(w.lower() in err.lower() for w in c.warns):
        return "wrong-exit", f"exit 0 without a warning ({' or '.join(c.warns)})"
    if problems:
        return "wrong-exit", "; ".join(problems)[:300]
    bad = [a for a in c.absent if os.path.lexists(d / a)]
    if bad:
        return "wrong-exit", "created " + ", ".join(bad)
    return "pass", ""


def run_case(c: Case, work: Path, fx: Path, ports: dict[str, int]) -> dict[str, Any]:
    d = work / "cases" / c.id
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    row: dict[str, Any] = {"id": c.id, "family": c.family, "what": c.what, "from_issue": c.from_issue}
    try:
        if c.setup:
            c.setup(d, fx)
    except Exception as exc:  # noqa: BLE001 - a setup that cannot run here is reported, not fatal
        for fd in _LOCKS.pop(d, []):
            os.close(fd)
        return {**row, "command": "", "exit": None, "outcome": "skipped", "detail": f"setup: {exc!r}"[:300],
                "stderr": "", "seconds": 0.0}
    argv = [fill(a, d, ports) for a in c.argv]
    cmd = c.raw if c.raw is not None else GRL + argv
    before = snapshot(d)
    extra: dict[str, str] = {}
    tag = ""
    if c.ray:
        tag = f"/tmp/grl-ray-{os.getpid()}-{c.id}"[:60]
        extra["RAY_TMPDIR"] = tag
    env = child_env(extra)
    try:
        code, out, err, secs = _run(cmd, d, env, c)
    except OSError as exc:  # the command could not start at all (an argument list too long): the case is wrong
        return {**row, "command": " ".join(argv)[:300], "exit": None, "outcome": "skipped",
                "detail": f"could not start: {exc}"[:300], "stderr": "", "seconds": 0.0}
    problems = [f"temporaries or lock left: {', '.join(left[:4])}" for left in [leftovers(d)] if left] \
        if c.signal_at is not None else []
    if c.then and code is not None:
        then = Case(c.id, c.family, c.what, c.then, expect=OK, timeout=c.timeout, ray=c.ray)
        code2, out2, err2, secs2 = _run(GRL + [fill(a, d, ports) for a in c.then], d, env, then)
        out, err, secs = out + out2, err + "\n" + err2, secs + secs2
        if code2 is None or code2 < 0 or code2 in (134, 139):
            code = code2
        elif code2 != 0:
            problems.append(f"the follow-up 'genesis-rl {' '.join(c.then)}' exited {code2}: {message(err2)}")
    for fd in _LOCKS.pop(d, []):
        os.close(fd)
    if tag:
        _end_ray(tag)
        shutil.rmtree(tag, ignore_errors=True)
    after = snapshot(d)
    lost = [k for k, v in before.items() if after.get(k) != v
            and not any(k == m or k.startswith(m.rstrip("/") + "/") for m in c.may_change)]
    outcome, detail = judge(c, d, code, out, err, lost, problems)
    shown = argv if c.raw is None else c.raw
    return {**row, "command": ("genesis-rl " if c.raw is None else "") + " ".join(shown), "exit": code,
            "outcome": outcome, "detail": detail, "stderr": message(err), "seconds": round(secs, 1)}


# -- report ----------------------------------------------------------------------------------------------------
def _cell(text: str, n: int) -> str:
    text = text.replace("|", "\\|").replace("\n", " ")
    return text if len(text) <= n else text[: n - 3] + "..."


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["# Hostile-input sweep (issue 38)", "",
             "Made by `tests/hostile/sweep_files.py`; one row a case. Outcomes: pass, code-exec, data-loss, abort, "
             "traceback, timeout, wrong-exit (see the script's docstring). Cases marked * are the issue's own "
             "examples; the others are new.", "",
             "| family | cases | new | " + " | ".join(OUTCOMES) + " |",
             "| --- | --- | --- | " + " | ".join("---" for _ in OUTCOMES) + " |"]
    for fam, title in FAMILIES.items():
        rs = [r for r in rows if r["family"] == fam]
        counts = [sum(1 for r in rs if r["outcome"] == o) for o in OUTCOMES]
        lines.append(f"| {fam}. {title} | {len(rs)} | {sum(1 for r in rs if not r['from_issue'])} | "
                     + " | ".join(map(str, counts)) + " |")
    total = [sum(1 for r in rows if r["outcome"] == o) for o in OUTCOMES]
    lines.append(f"| all | {len(rows)} | {sum(1 for r in rows if not r['from_issue'])} | "
                 + " | ".join(map(str, total)) + " |")
    bad = [r for r in rows if r["outcome"] not in ("pass", "skipped")]
    if bad:
        lines += ["", "## What fails, by family", ""]
        for fam, title in FAMILIES.items():
            rs = [r for r in bad if r["family"] == fam]
            if rs:
                lines.append(f"- **{fam}. {title}** ({len(rs)}): "
                             + "; ".join(f"`{r['id']}` {r['outcome']} ({_cell(r['detail'], 90)})" for r in rs))
    for fam, title in FAMILIES.items():
        rs = [r for r in rows if r["family"] == fam]
        if not rs:
            continue
        lines += ["", f"## {fam}. {title}", "", "| id | what | command | exit | outcome | stderr (last line) |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for r in rs:
            outcome = r["outcome"] if r["outcome"] == "pass" else f"**{r['outcome']}**: {r['detail']}"
            lines.append(f"| {r['id']}{'*' if r['from_issue'] else ''} | {_cell(r['what'], 80)} | "
                         f"`{_cell(r['command'], 100)}` | {r['exit']} | {_cell(outcome, 160)} | "
                         f"{_cell(r['stderr'], 160)} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="sweep.json", help="JSON of every case and its outcome")
    ap.add_argument("--markdown", default=None, help="also write the Markdown table here")
    ap.add_argument("--family", type=int, action="append", choices=sorted(FAMILIES), help="only these families")
    ap.add_argument("--ids", default=None, help="comma list of case ids (or id prefixes)")
    ap.add_argument("--limit", type=int, default=None, help="at most this many cases (after the filters)")
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once (default: 2)")
    ap.add_argument("--work", default=None, help="work folder (fixtures are kept and reused there); default: a "
                                                 "new temporary folder, removed afterwards")
    ap.add_argument("--all", action="store_true", help="every case, the whole value grids too (about twice as long)")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--render", default=None, metavar="JSON", help="only write --markdown from an earlier --out JSON")
    args = ap.parse_args(argv)
    if args.render:
        Path(args.markdown or "sweep.md").write_text(markdown(json.loads(Path(args.render).read_text())["results"]))
        return 0
    build_cases()
    todo = [c for c in CASES if (args.all or c.core or args.ids) and (not args.family or c.family in args.family)
            and (not args.ids or any(c.id == i or c.id.startswith(i) for i in args.ids.split(",")))]
    todo = todo[: args.limit] if args.limit else todo
    if args.list:
        for c in todo:
            print(f"{c.id:40s} {c.what}")
        print(f"{len(todo)} cases ({sum(1 for c in todo if not c.from_issue)} new)")
        return 0
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="grl-sweep-"))
    work.mkdir(parents=True, exist_ok=True)

    def log(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    fx = work / "fixtures"
    needed = any(c.setup is not None for c in todo)
    if needed:
        make_fixtures(fx, log)
    fx_before = snapshot(fx) if needed else {}
    ports = start_listeners()
    t0 = time.time()
    rows: list[dict[str, Any]] = []
    lock = threading.Lock()

    def save(final: bool) -> None:
        """The JSON (and Markdown) so far, rewritten after every case: a long sweep can be read while it runs."""
        ordered = sorted(rows, key=lambda r: [c.id for c in todo].index(r["id"]))
        report = {"schema": "genesis-rl/hostile-sweep", "version": 1, "complete": final, "cases": len(ordered),
                  "planned": len(todo), "new_cases": sum(1 for r in ordered if not r["from_issue"]),
                  "seconds": round(time.time() - t0, 1),
                  "counts": {str(f): {o: sum(1 for r in ordered if r["family"] == f and r["outcome"] == o)
                                      for o in (*OUTCOMES, "skipped")} for f in FAMILIES},
                  "results": ordered}
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
        if args.markdown:
            Path(args.markdown).write_text(markdown(ordered))

    def one(c: Case) -> dict[str, Any]:
        r = run_case(c, work, fx, ports)
        with lock:
            rows.append(r)
            save(False)
            log(f"[{len(rows):3d}/{len(todo)}] {r['id']:38s} {r['outcome']:10s} exit {str(r['exit']):>4} "
                f"{r['seconds']:5.1f}s {(r['detail'] or r['stderr'])[:110]}")
        return r

    with ThreadPoolExecutor(max(1, args.jobs)) as pool:  # each case is a subprocess: threads only wait
        list(pool.map(one, todo))
    if needed and snapshot(fx) != fx_before:
        log("warning: a case changed the shared fixtures")
    save(True)
    bad = [r for r in rows if r["outcome"] not in ("pass", "skipped")]
    log(f"{len(rows)} cases in {time.time() - t0:.0f} s: {len(rows) - len(bad)} pass, {len(bad)} fail "
        + str({o: sum(1 for r in bad if r['outcome'] == o) for o in OUTCOMES[1:]}))
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if bad else 0


# -- the cases -------------------------------------------------------------------------------------------------
def build_cases() -> None:
    if CASES:
        return
    family1()
    family2()
    family3()
    family4()
    family5()
    family6()
    ids = [c.id for c in CASES]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise SystemExit(f"duplicate case ids: {dup}")


def iter_values() -> Iterable[tuple[str, str, str]]:
    """(name, JSON literal, TOML literal) of the hostile values every numeric field is swept with."""
    yield from (("zero", "0", "0"), ("neg", "-1", "-1"), ("tiny", "1e-320", "1e-320"), ("huge", "1e308", "1e308"),
                ("inf", "Infinity", "inf"), ("nan", "NaN", "nan"), ("str", '"str"', '"str"'),
                ("bool", "true", "true"), ("list", "[]", "[]"))



# -- commands the cases share (tiny sizes: one scene, a few steps, 64x48 cameras) ----------------------------------
EVAL = "evaluate --catalog cat.json --policies sunny --scenes 1 --steps 5 --system blind --quiet --no-report --no-counterfactual"
EVAL_HW = EVAL.replace("cat.json", "hw.json")
EVAL_AGENT = "evaluate --agent run --policies agent --catalog hw.json --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out e"
DRIVE = "drive --catalog cat.json --steps 5 --system blind --no-gif --quiet --width 64 --height 48 --out dv"
RENDER = "render --catalog cat.json --width 64 --height 48 --out r"
CORNERS = "corners --config c.toml --scenes 1 --steps 3 --quiet --out corners.json"
TRAIN = "train --config c.toml --out r --steps 8 --n-steps 8 --quiet"
RESUME = "train --out run --resume --steps 48 --quiet"
REPLAY = "replay rec.json --out rp --no-gif --quiet"
CAMP = cp("camp")
# the fixture campaign's own command, resumed (a campaign resumes only with the settings it was run with)
RESUME_CAMP = ("evaluate --agent run --catalog hw.json --policies sunny,agent --scenes 3 --seed 1 --steps 70 --system blind "
               "--records failures --no-counterfactual --out camp --resume --quiet --no-report")
RUN = cp("run")
CARLA = "scenes --backend carla --count 1 --out c.json --quiet"


def toml_set(text: str, table: str, key: str, literal: str) -> str:
    """Set ``key = literal`` in ``[table]`` of a TOML text (added, with the table, where missing)."""
    lines = text.splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.strip() == f"[{table}]"), None)
    if start is None:
        return text.rstrip("\n") + f"\n\n[{table}]\n{key} = {literal}\n"
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("[")), len(lines))
    for i in range(start + 1, end):
        if re.match(rf"\s*{re.escape(key)}\s*=", lines[i]):
            lines[i] = f"{key} = {literal}"
            return "\n".join(lines) + "\n"
    lines.insert(start + 1, f"{key} = {literal}")
    return "\n".join(lines) + "\n"


def config(table: str, key: str, literal: str, base: str = "tiny.toml", name: str = "c.toml") -> Setup:
    def setup(d: Path, fx: Path) -> None:
        (d / name).write_text(toml_set((fx / base).read_text(), table, key, literal))
    return setup


def family1() -> None:
    """Outputs onto their own inputs, into input folders, onto links, FIFOs and devices. An output folder that
    holds an input may be refused or written (exit 0 or 2), as long as the input is kept."""
    R = "report camp"
    case(1, "report-onto-campaign-json", "report --out the campaign's campaign.json --force", f"{R} --out camp/campaign.json --force", setup=CAMP, from_issue=True)
    for rel in ("summary.json", "episodes.csv", "catalog.json", "run_time.json", "@GLOB:camp/episodes/sunny/*.json@", "@GLOB:camp/records/*.json@", "@GLOB:camp/steps/agent/*.parquet@"):
        slug = re.sub(r"\W+", "-", rel.replace("@GLOB:camp/", "").rstrip("@").replace("*", "x")).strip("-")
        case(1, f"report-onto-{slug}", f"report --out onto the campaign's own {rel} --force", f"{R} --out {rel if rel.startswith('@') else 'camp/' + rel} --force", setup=CAMP,
             core=rel in ("summary.json", "episodes.csv", "@GLOB:camp/records/*.json@", "@GLOB:camp/steps/agent/*.parquet@"))
    case(1, "report-onto-campaign-folder", "report --out the campaign folder itself --force", f"{R} --out camp --force", setup=CAMP)
    case(1, "report-into-records", "report --out the campaign's records folder --force", f"{R} --out camp/records --force", setup=CAMP)
    case(1, "report-onto-link-to-input", "report --out a symlink to the campaign's campaign.json --force", f"{R} --out link.html --force", setup=chain(CAMP, symlink("link.html", "camp/campaign.json")))
    case(1, "report-onto-hardlink", "report --out a hard link of campaign.json --force (the campaign's file itself)", f"{R} --out hard.html --force", setup=chain(CAMP, hardlink("hard.html", "camp/campaign.json")), may_change=("hard.html",))
    case(1, "report-onto-fifo", "report --out a FIFO nobody reads --force", f"{R} --out pipe --force", setup=chain(CAMP, fifo("pipe")), timeout=30)
    case(1, "report-onto-device", "report --out a character device (a null device node) --force", f"{R} --out nulldev --force", setup=chain(CAMP, devnull("nulldev")), expect=EITHER)
    case(1, "report-onto-stdout-link", "report --out a symlink to /proc/self/fd/1 --force", f"{R} --out so --force", setup=chain(CAMP, symlink("so", "/proc/self/fd/1")), expect=EITHER)
    case(1, "report-dash", "report --out - writes to stdout, not a file named '-'", f"{R} --out -", setup=CAMP, expect=OK, absent=("-",))
    case(1, "report-onto-user-link", "report --out a symlink to the user's own notes --force: written through or refused, the link kept", f"{R} --out l.html --force", setup=chain(CAMP, write("notes.html", "mine"), symlink("l.html", "notes.html")), expect=EITHER, may_change=("notes.html",))
    C = "compare a=camp:sunny b=camp:agent"
    case(1, "compare-onto-campaign-json", "compare --json the campaign's campaign.json --force", f"{C} --json camp/campaign.json --force", setup=CAMP, from_issue=True)
    for rel in ("summary.json", "episodes.csv", "@GLOB:camp/records/*.json@"):
        slug = re.sub(r"\W+", "-", rel.replace("@GLOB:camp/", "").rstrip("@").replace("*", "x")).strip("-")
        case(1, f"compare-onto-{slug}", f"compare --json onto the campaign's {rel} --force", f"{C} --json {rel if rel.startswith('@') else 'camp/' + rel} --force", setup=CAMP)
    case(1, "compare-onto-link", "compare --json a symlink to the campaign's summary.json --force", f"{C} --json s.json --force", setup=chain(CAMP, symlink("s.json", "camp/summary.json")))
    case(1, "compare-onto-fifo", "compare --json a FIFO nobody reads", f"{C} --json pipe --force", setup=chain(CAMP, fifo("pipe")), timeout=30)
    case(1, "compare-dash", "compare --json - writes to stdout", f"{C} --json -", setup=CAMP, expect=OK, absent=("-",))
    case(1, "compare-onto-folder", "compare --json the campaign folder --force", f"{C} --json camp --force", setup=CAMP)
    RX = "reactivity --campaign camp --policy sunny --scenes 2 --no-other-seeds --quiet"
    case(1, "reactivity-onto-campaign-json", "reactivity --out the campaign's campaign.json --force", f"{RX} --out camp/campaign.json --force", setup=CAMP)
    case(1, "reactivity-onto-episodes-csv", "reactivity --out the campaign's episodes.csv --force", f"{RX} --out camp/episodes.csv --force", setup=CAMP)
    case(1, "export-onto-campaign", "export --out the campaign folder itself --force", "export camp --out camp --force", setup=CAMP)
    case(1, "export-into-records", "export --out the campaign's records folder --force", "export camp --out camp/records --force", setup=CAMP)
    case(1, "export-onto-run", "export --out a training run folder --force", "export camp --out run --force", setup=chain(CAMP, RUN))
    case(1, "export-onto-user-folder", "export --out a user's folder holding notes --force", "export camp --out ex --force", setup=chain(CAMP, write("ex/notes.txt", "mine")))
    case(1, "replay-out-holds-record", "replay --out the folder holding the record --force", "replay recs/rec.json --out recs --no-gif --quiet --force", setup=cp("rec.json", to="recs/rec.json"), expect=EITHER)
    case(1, "replay-out-campaign", "replay a campaign's record --out the campaign folder --force", "replay @GLOB:camp/records/*.json@ --out camp --no-gif --quiet --force", setup=CAMP, expect=EITHER)
    case(1, "replay-out-cwd", "replay --out . (the folder holding the record) --force", "replay rec.json --out . --no-gif --quiet --force", setup=cp("rec.json"), expect=EITHER)
    case(1, "render-out-holds-catalog", "render --out the folder holding its --catalog --force", "render --catalog o/cat.json --width 64 --height 48 --out o --force", setup=cp("cat.json", to="o/cat.json"), expect=EITHER)
    case(1, "drive-out-holds-catalog", "drive --out the folder holding its --catalog --force", "drive --catalog o/cat.json --steps 5 --system blind --no-gif --quiet --width 64 --height 48 --out o --force", setup=cp("cat.json", to="o/cat.json"), expect=EITHER)
    case(1, "drive-out-holds-schedule", "drive --out the folder holding its --schedule --force", "drive --catalog cat.json --schedule o/sched.csv --steps 5 --system blind --no-gif --quiet --width 64 --height 48 --out o --force", setup=chain(cp("cat.json"), cp("sched.csv", to="o/sched.csv")), expect=EITHER)
    case(1, "drive-out-cwd", "drive --out . with its catalog in it --force", "drive --catalog cat.json --steps 5 --system blind --no-gif --quiet --width 64 --height 48 --out . --force", setup=cp("cat.json"), expect=EITHER)
    case(1, "evaluate-onto-run", "evaluate --agent run --out run --force (a campaign over its own agent)", "evaluate --agent run --policies agent --catalog hw.json --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out run --force", setup=chain(RUN, cp("hw.json")))
    case(1, "evaluate-into-checkpoints", "evaluate --out the run's checkpoints folder --force", "evaluate --agent run --policies agent --catalog hw.json --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out run/checkpoints --force", setup=chain(RUN, cp("hw.json")))
    case(1, "evaluate-out-holds-catalog", "evaluate --out the folder holding its --catalog --force", f"{EVAL.replace('cat.json', 'ev/cat.json')} --out ev --force", setup=cp("cat.json", to="ev/cat.json"), expect=EITHER)
    case(1, "evaluate-out-holds-odd", "evaluate --out the folder holding its --odd --force", f"{EVAL_HW} --odd ev/odd.toml --out ev --force", setup=chain(cp("hw.json"), cp("odd.toml", to="ev/odd.toml")), expect=EITHER)
    case(1, "evaluate-out-holds-config", "evaluate --config inside --out --force", "evaluate --config ev/c.toml --catalog cat.json --policies sunny --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out ev --force", setup=chain(cp("cat.json"), cp("tiny.toml", to="ev/c.toml")), expect=EITHER)
    case(1, "evaluate-onto-campaign-with-notes", "evaluate --out an existing campaign holding a user's notes --force", f"{EVAL_HW} --out camp --force", setup=chain(CAMP, cp("hw.json"), write("camp/notes.txt", "mine")))
    case(1, "train-force-notes", "train --out RUN --force with a user's notes in RUN", "train --config tiny.toml --out run --force --quiet", setup=chain(RUN, cp("tiny.toml"), write("run/notes.txt", "mine")), from_issue=True)
    case(1, "train-force-eval-campaign", "train --out RUN --force with an eval/ campaign kept in RUN", "train --config tiny.toml --out run --force --quiet", setup=chain(RUN, cp("tiny.toml"), cp("camp", to="run/eval")), from_issue=True)
    case(1, "train-config-inside-out", "train --config RUN/config.toml --out RUN --force", "train --config run/config.toml --out run --force --quiet", setup=RUN, expect=EITHER)
    case(1, "train-catalog-inside-out", "train --catalog RUN/catalog.json --out RUN --force", "train --config tiny.toml --catalog run/catalog.json --out run --force --quiet", setup=chain(RUN, cp("tiny.toml")), expect=EITHER)
    case(1, "train-odd-inside-out", "train --odd inside --out --force", "train --config tiny.toml --odd run/odd.toml --out run --force --quiet", setup=chain(RUN, cp("tiny.toml"), cp("odd.toml", to="run/odd.toml")), expect=EITHER)
    case(1, "train-onto-campaign", "train --out a campaign folder --force", "train --config tiny.toml --out camp --force --quiet", setup=chain(CAMP, cp("tiny.toml")))
    case(1, "train-out-cwd", "train --out . (holding its --config) --force", "train --config tiny.toml --out . --force --quiet", setup=cp("tiny.toml"), expect=EITHER)
    case(1, "corners-onto-config", "corners --out its own --config --force", "corners --config c.toml --scenes 1 --steps 3 --quiet --out c.toml --force", setup=cp("tiny.toml", to="c.toml"))
    case(1, "corners-onto-fifo", "corners --out a FIFO", "corners --config c.toml --scenes 1 --steps 3 --quiet --out pipe --force", setup=chain(cp("tiny.toml", to="c.toml"), fifo("pipe")), timeout=30)
    case(1, "corners-onto-run-config", "corners --config RUN/config.toml --out RUN/config.toml --force", "corners --config run/config.toml --scenes 1 --steps 3 --quiet --out run/config.toml --force", setup=RUN)
    case(1, "scenes-onto-fifo", "scenes --out a FIFO", "scenes --count 1 --out pipe --force --quiet", setup=fifo("pipe"), timeout=30)
    case(1, "scenes-onto-device", "scenes --out a character device --force", "scenes --count 1 --out nulldev --force --quiet", setup=devnull("nulldev"), expect=EITHER)
    case(1, "scenes-onto-user-link", "scenes --out a symlink to the user's file --force: written through or refused, the link kept", "scenes --count 1 --out l.json --force --quiet", setup=chain(write("mine.json", "{}"), symlink("l.json", "mine.json")), expect=EITHER, may_change=("mine.json",))
    case(1, "scenes-dash", "scenes --out - writes to stdout", "scenes --count 1 --out - --quiet", expect=OK, absent=("-",))
    case(1, "map-onto-fifo", "map --out a FIFO", "map export --out pipe --force", setup=fifo("pipe"), timeout=30)
    case(1, "map-onto-run-folder", "map --out a run folder --force", "map export --out run --force", setup=RUN)
    case(1, "map-dash", "map --out - writes to stdout", "map export --out -", expect=OK, absent=("-",))


def family2() -> None:
    """Payloads whose loading would create the marker file: pickles in agents, checkpoints, replay buffers;
    import paths named by run, campaign, record and catalog files."""
    for entry in ("lr_schedule", "clip_range", "policy_class", "observation_space", "action_space", "_last_obs"):
        case(2, f"agent-data-{entry}", f"agent.zip 'data' {entry} holds a pickled payload; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), zip_member("run/agent.zip", "data", serialized(entry))), expect=EITHER, from_issue=entry == "lr_schedule")
    case(2, "agent-zip-loose", "a loose agent .zip with a pickled lr_schedule as --agent", EVAL_AGENT.replace("--agent run", "--agent a.zip"), setup=chain(cp("run/agent.zip", to="a.zip"), cp("hw.json"), zip_member("a.zip", "data", serialized("lr_schedule"))), expect=EITHER)
    for member in ("policy.pth", "pytorch_variables.pth", "policy.optimizer.pth"):
        case(2, f"agent-{member.replace('.', '-')}", f"agent.zip {member} is a torch pickle with a payload", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), zip_member("run/agent.zip", member, lambda d, old: torch_payload(d))), expect=EITHER)
    case(2, "checkpoint-data-lr-schedule", "the last checkpoint's 'data' holds a pickled payload; train --resume", RESUME, setup=chain(RUN, zip_member("run/checkpoints/step_00000032.zip", "data", serialized("lr_schedule"))), expect=EITHER)
    case(2, "checkpoint-policy-pth", "the last checkpoint's policy.pth is a torch pickle with a payload; train --resume", RESUME, setup=chain(RUN, zip_member("run/checkpoints/step_00000032.zip", "policy.pth", lambda d, old: torch_payload(d))), expect=EITHER)
    case(2, "checkpoint-optimizer-pth", "the last checkpoint's policy.optimizer.pth holds a payload; train --resume", RESUME, setup=chain(RUN, zip_member("run/checkpoints/step_00000032.zip", "policy.optimizer.pth", lambda d, old: torch_payload(d))), expect=EITHER)
    case(2, "evaluate-agent-no-agent-zip", "no agent.zip: evaluate --agent falls back to a checkpoint holding a payload", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), lambda d, fx: (d / "run/agent.zip").unlink(), zip_member("run/checkpoints/last.zip", "data", serialized("clip_range"))), expect=EITHER)
    case(2, "sac-replay-buffer", "a SAC run's replay buffer (.pkl) holds a payload; train --resume", "train --out sacrun --resume --steps 36 --quiet", setup=chain(cp("sacrun"), write("sacrun/checkpoints/step_00000024.replay.pkl", b""), lambda d, fx: (d / "sacrun/checkpoints/step_00000024.replay.pkl").write_bytes(payload(d))), expect=EITHER)
    case(2, "sac-agent-data", "a SAC run's agent.zip 'data' holds a payload; evaluate --agent", EVAL_AGENT.replace("--agent run", "--agent sacrun"), setup=chain(cp("sacrun"), cp("hw.json"), zip_member("sacrun/agent.zip", "data", serialized("lr_schedule"))), expect=EITHER)
    case(2, "detector-weights-pickle", "--weights: a detector checkpoint that is a torch pickle with a payload", "drive --catalog cat.json --steps 2 --system builtin --weights w.pt --no-gif --quiet --width 64 --height 48 --out dv", setup=chain(cp("cat.json"), lambda d, fx: (d / "w.pt").write_bytes(torch_payload(d))))
    ev = evil_module()
    case(2, "run-config-system", "the run's config.toml names env.system = 'evil:Sys' (a module in the working folder)", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), ev, edit_text("run/config.toml", lambda t: toml_set(t, "env", "system", '"evil:Sys"'))))
    case(2, "run-config-plugins", "the run's config.toml names env.plugins = ['evil']", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), ev, edit_text("run/config.toml", lambda t: toml_set(t, "env", "plugins", '["evil"]'))))
    case(2, "run-config-backend", "the run's config.toml names env.backend = 'evil:Backend'", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), ev, edit_text("run/config.toml", lambda t: toml_set(t, "env", "backend", '"evil:Backend"'))))
    case(2, "run-config-rulebook-rule", "the run's config.toml names a rulebook whose rule is 'evil:Rule'", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), ev, write("run/rules.toml", '[[rules]]\nname = "evil:Rule"\npriority = 1\n'), edit_text("run/config.toml", lambda t: toml_set(t, "env", "rulebook", '"run/rules.toml"'))))
    case(2, "resume-config-plugins", "the run's config.toml names env.plugins = ['evil']; train --resume", RESUME, setup=chain(RUN, ev, edit_text("run/config.toml", lambda t: toml_set(t, "env", "plugins", '["evil"]'))))
    case(2, "resume-config-system", "the run's config.toml names env.system = 'evil:Sys'; train --resume", RESUME, setup=chain(RUN, ev, edit_text("run/config.toml", lambda t: toml_set(t, "env", "system", '"evil:Sys"'))))
    case(2, "campaign-system", "campaign.json's spec names env.system = 'evil:Sys'; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), ev, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "env", "system"], "evil:Sys"))))
    case(2, "campaign-plugins", "campaign.json's spec names env.plugins = ['evil']; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), ev, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "env", "plugins"], ["evil"]))))
    case(2, "campaign-policy", "campaign.json's spec names a policy 'evil:Pol'; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), ev, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "policies"], ["sunny", "evil:Pol"]))))
    case(2, "campaign-system-reactivity", "campaign.json's spec names env.system = 'evil:Sys'; reactivity", "reactivity --campaign camp --policy sunny --scenes 2 --no-other-seeds --quiet --out rx.json", setup=chain(CAMP, ev, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "env", "system"], "evil:Sys"))))
    case(2, "campaign-system-report", "campaign.json's spec names env.system = 'evil:Sys'; report", "report camp --out rep.html", setup=chain(CAMP, ev, edit_json("camp/campaign.json", lambda c: set_path(c, ["spec", "env", "system"], "evil:Sys"))), expect=EITHER)
    case(2, "record-system", "a record's system spec is 'evil:Sys'; replay", REPLAY, setup=chain(cp("rec.json"), ev, edit_json("rec.json", lambda r: set_path(r, ["system", "spec"], "evil:Sys"))))
    case(2, "record-backend", "a record's backend is 'evil:Backend'; replay", REPLAY, setup=chain(cp("rec.json"), ev, edit_json("rec.json", lambda r: set_path(r, ["backend"], "evil:Backend"))))
    case(2, "catalog-backend", "a catalog's backend is 'evil:Backend'; render", RENDER, setup=chain(cp("cat.json"), ev, edit_json("cat.json", lambda c: set_path(c, ["backend"], "evil:Backend"))))
    case(2, "catalog-backend-drive", "a catalog's backend is 'evil:Backend'; drive", DRIVE, setup=chain(cp("cat.json"), ev, edit_json("cat.json", lambda c: set_path(c, ["backend"], "evil:Backend"))))


CORE_VALUES = ("neg", "huge", "nan", "str")  # the default sweep's share of each value grid; --all runs all nine


def expect_for(value: str, signed: bool) -> tuple[int, ...]:
    """0 and 1e-320 may be valid (or refused); -1 too where the field is signed; the rest must be refused."""
    if value in ("zero", "tiny") or (signed and value == "neg"):
        return EITHER
    return REJECT


def family3() -> None:
    """Every numeric field swept with 0, -1, 1e-320, 1e308, inf, nan, a string, a bool and a list; files that
    are believed when they should be checked."""
    cat_fields = [("ego-speed", ["scenes", 0, "vehicles", 0, "speed"], False),
                  ("ego-x", ["scenes", 0, "vehicles", 0, "x"], True),
                  ("ego-yaw", ["scenes", 0, "vehicles", 0, "yaw"], True),
                  ("lead-max-accel", ["scenes", 0, "vehicles", 1, "autopilot", "max_accel"], False),
                  ("lead-comfort-decel", ["scenes", 0, "vehicles", 1, "autopilot", "comfort_decel"], False),
                  ("lead-time-gap", ["scenes", 0, "vehicles", 1, "autopilot", "time_gap"], False),
                  ("signal-offset", ["scenes", 0, "signal_offset"], True)]
    for name, path, signed in cat_fields:
        for vname, js, _ in iter_values():
            case(3, f"catalog-{name}-{vname}", f"catalog scene 0 {'.'.join(map(str, path[3:]))} = {js}; drive", DRIVE,
                 setup=chain(cp("cat.json"), edit_text("cat.json", _json_setter(path, js))), expect=expect_for(vname, signed), names=(str(path[-1]),),
                 core=vname in CORE_VALUES or (name in ("ego-speed", "lead-comfort-decel") and vname in ("tiny", "inf")))
    case(3, "catalog-ego-speed-1000", "catalog ego speed 1000 m/s; drive", DRIVE, setup=chain(cp("cat.json"), edit_text("cat.json", _json_setter(["scenes", 0, "vehicles", 0, "speed"], "1000"))), from_issue=True)
    case(3, "catalog-ego-speed-1e200", "catalog ego speed 1e200; drive", DRIVE, setup=chain(cp("cat.json"), edit_text("cat.json", _json_setter(["scenes", 0, "vehicles", 0, "speed"], "1e200"))), from_issue=True)
    for vname, js in (("true", "true"), ("float", "1.0"), ("str", '"1"'), ("big", "2"), ("null", "null")):
        case(3, f"catalog-version-{vname}", f"catalog \"version\": {js}; render", RENDER, setup=chain(cp("cat.json"), edit_text("cat.json", _json_setter(["version"], js))), from_issue=vname == "true",
             expect=EITHER if vname == "float" else REJECT)  # 1.0 == 1
    case(3, "catalog-map-mismatch", "an urban catalog evaluated under --map highway", EVAL.replace("--scenes 1", "--map highway --scenes 1") + " --out e", setup=cp("cat.json"), from_issue=True)
    case(3, "catalog-header-map-lies", "catalog header map = highway over urban scenes; drive", DRIVE, setup=chain(cp("cat.json"), edit_json("cat.json", lambda c: set_path(c, ["map"], "highway"))))
    case(3, "catalog-scene-map-lies", "catalog scene 0 map = highway in an urban catalog; drive", DRIVE, setup=chain(cp("cat.json"), edit_json("cat.json", lambda c: set_path(c, ["scenes", 0, "map"], "highway"))))
    case(3, "catalog-lane-out-of-range", "catalog ego lane = 10**9; drive", DRIVE, setup=chain(cp("cat.json"), edit_text("cat.json", _json_setter(["scenes", 0, "vehicles", 0, "lane"], "1000000000"))))
    case(3, "catalog-color-nan", "catalog ego colour [NaN, 2, -1]; render", RENDER, setup=chain(cp("cat.json"), edit_text("cat.json", _json_setter(["scenes", 0, "vehicles", 0, "color"], "[NaN, 2, -1]"))))
    for key, vname in (("distance", "prox"), ("decel", "rss")):
        for v, _, tl in iter_values():
            case(3, f"rulebook-{vname}-{key}-{v}", f"rulebook {key} = {tl}; evaluate --config", "evaluate --config rcfg.toml --catalog cat.json --policies sunny --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out e",
                 setup=chain(cp("rcfg.toml", "rules.toml", "cat.json"), edit_text("rules.toml", _toml_param(key, tl))), expect=expect_for(v, False), from_issue=(key, v) == ("decel", "tiny"), names=(key,),
                 core=v in CORE_VALUES or key == "decel")
    for v, lit in (("str", '"high"'), ("neg", "-1"), ("huge", "1e308")):
        case(3, f"rulebook-priority-{v}", f"rulebook priority = {lit}; evaluate --config", "evaluate --config rcfg.toml --catalog cat.json --policies sunny --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out e",
             setup=chain(cp("rcfg.toml", "rules.toml", "cat.json"), edit_text("rules.toml", _sub("priority = 2", f"priority = {lit}"))))
    odd_fields = [("visibility-min", "visibility", "min"), ("rain-max", "rain_rate", "max"), ("margin", None, "boundary_margin")]
    for name, table, key in odd_fields:
        for v, _, tl in iter_values():
            case(3, f"odd-{name}-{v}", f"ODD {table + '.' if table else ''}{key} = {tl}; evaluate --odd", f"{EVAL_HW} --odd odd.toml --out e",
                 setup=chain(cp("hw.json", "odd.toml"), edit_text("odd.toml", _toml_key(table, key, tl))), expect=expect_for(v, True), names=(table or key,),
                 core=v in CORE_VALUES)
    cfg_fields = [("env", "max_step_fraction"), ("env", "start_spread"), ("env.reward", "collision_weight"), ("ppo", "learning_rate"), ("ppo", "gamma"), ("ppo", "clip_range")]
    for table, key in cfg_fields:
        for v, _, tl in iter_values():
            if v in ("zero", "bool", "list"):
                continue
            case(3, f"config-{table.replace('.', '-')}-{key.replace('_', '-')}-{v}", f"config [{table}] {key} = {tl}; train", TRAIN,
                 setup=config(table, key, tl), expect=expect_for(v, False), names=(key,), from_issue=(key, v) in (("max_step_fraction", "tiny"), ("collision_weight", "huge")),
                 core=v in ("tiny", "huge", "nan"))
    for v, cell in (("nan", "nan"), ("inf", "inf"), ("neg", "-1"), ("huge", "1e308"), ("str", "heavy"), ("empty", ""), ("tiny", "1e-320")):
        case(3, f"schedule-cell-{v}", f"schedule CSV fog_density cell = '{cell}'; drive --schedule", DRIVE + " --schedule s.csv",
             setup=chain(cp("cat.json"), cp("sched.csv", to="s.csv"), edit_text("s.csv", _sub("2,20,10", f"2,{cell},10"))), expect=EITHER if v == "tiny" else REJECT, names=("s.csv",))
    for v, js in (("fog-nan", "NaN"), ("fog-huge", "1e308")):
        case(3, f"record-weather-{v}", f"record start_weather fog_density = {js}; replay", REPLAY, setup=chain(cp("rec.json"), edit_text("rec.json", _json_setter(["start_weather", "fog_density"], js))), expect=(1, 2))
    case(3, "record-ego-speed-1e200", "record scene ego speed = 1e200; replay", REPLAY, setup=chain(cp("rec.json"), edit_text("rec.json", _json_setter(["scene", "vehicles", 0, "speed"], "1e200"))), expect=(1, 2), from_issue=True)
    case(3, "record-schedule-inf", "record schedule step 0 holds Infinity; replay", REPLAY, setup=chain(cp("rec.json"), edit_text("rec.json", _json_setter(["schedule", 0, 0], "Infinity"))), expect=(1, 2))
    case(3, "record-episode-seed-str", "record episode_seed = 'x'; replay", REPLAY, setup=chain(cp("rec.json"), edit_text("rec.json", _json_setter(["episode_seed"], '"x"'))))
    # a run is pinned like a campaign
    case(3, "run-empty-config", "the run's config.toml is empty; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), write("run/config.toml", "")), from_issue=True)
    case(3, "run-edited-config-resume", "the run's config.toml edited (episode_steps 10 -> 12); train --resume", RESUME, setup=chain(RUN, edit_text("run/config.toml", lambda t: t.replace("episode_steps = 10", "episode_steps = 12"))), from_issue=True)
    case(3, "run-edited-system-evaluate", "the run's config.toml edited (system blind -> oracle); evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), edit_text("run/config.toml", lambda t: t.replace('system = "blind"', 'system = "oracle"'))))
    case(3, "run-edited-obs-evaluate", "the run's config.toml edited (obs_history 4 -> 2); evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), edit_text("run/config.toml", lambda t: t.replace("obs_history = 4", "obs_history = 2"))))
    case(3, "run-edited-catalog-resume", "the run's catalog.json edited (a speed); train --resume", RESUME, setup=chain(RUN, edit_text("run/catalog.json", _json_setter(["scenes", 0, "vehicles", 0, "speed"], "3.0"))))
    case(3, "run-swapped-agent", "the run's agent.zip swapped for another run's; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), cp("sacrun/agent.zip", to="run/agent.zip")))
    case(3, "run-edited-knobs-resume", "the run's config.toml edited (a knob removed); train --resume", RESUME, setup=chain(RUN, edit_text("run/config.toml", lambda t: t.replace(', "sun_azimuth_angle"', ""))))
    case(3, "run-config-only-comment", "the run's config.toml holds only a comment; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), write("run/config.toml", "# nothing\n")))
    case(3, "run-still-locked", "evaluate --agent on a run whose lock is held (still training) warns or refuses", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), hold_lock(".run.genesis-rl.lock")), expect=EITHER,
         warns=("checkpoint",), names=("checkpoint", "being written", "still"))
    case(3, "campaign-edited-seeds-resume", "campaign.json's episode seeds edited; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), edit_json("camp/campaign.json", lambda c: set_path(c, ["scenes", 0, 1], 12345))))
    case(3, "campaign-steps-nan", "campaign.json's spec steps = NaN; report", "report camp --out rep.html", setup=chain(CAMP, edit_text("camp/campaign.json", _json_setter(["spec", "steps"], "NaN"))))
    case(3, "campaign-summary-inf", "summary.json holds Infinity; report", "report camp --out rep.html", setup=chain(CAMP, edit_text("camp/summary.json", lambda t: re.sub(r'("collision": )[-0-9.e]+', r"\1Infinity", t, count=1))), expect=EITHER,
         may_change=("camp/summary.json",))
    case(3, "episodes-csv-nan-return", "the campaign's episodes.csv return cell = nan; report", "report camp --out rep.html", setup=chain(CAMP, edit_text("camp/episodes.csv", lambda t: t.replace(",70.0,", ",nan,", 1))), expect=EITHER)
    case(3, "weather-flag-1e-320", "--weather fog_density=1e-320 (valid: tiny) ; drive", DRIVE + " --weather fog_density=1e-320", setup=cp("cat.json"), expect=EITHER)
    case(3, "constant-action-nan", "--constant-action nan,...; evaluate", EVAL.replace("sunny", "constant") + " --constant-action nan,0,0,0,0 --out e", setup=cp("cat.json"))
    case(3, "constant-action-1e308", "--constant-action 1e308,...; evaluate", EVAL.replace("sunny", "constant") + " --constant-action 1e308,0,0,0,0 --out e", setup=cp("cat.json"))


def _sub(old: str, new: str) -> Callable[[str], str]:
    return lambda text: text.replace(old, new, 1)


def _json_setter(path: Sequence[Any], literal: str) -> Callable[[str], str]:
    """Set a JSON value by path to a literal (NaN, Infinity, 1e-320 kept as written)."""
    def fn(text: str) -> str:
        data = json.loads(text)
        token = "__SWEEP_VALUE__"
        set_path(data, path, token)
        return json.dumps(data).replace(f'"{token}"', literal)
    return fn


def _toml_param(key: str, literal: str) -> Callable[[str], str]:
    return lambda t: re.sub(rf"({key} = )[-0-9.e]+", rf"\g<1>{literal}", t, count=1)


def _toml_key(table: str | None, key: str, literal: str) -> Callable[[str], str]:
    def fn(text: str) -> str:
        if table is None:
            return re.sub(rf"(?m)^{key}\s*=\s*[-0-9.e]+", f"{key} = {literal}", text, count=1)
        return re.sub(rf"(\[{table}\][^\[]*?\n){key}\s*=\s*[-0-9.e]+", rf"\g<1>{key} = {literal}", text, count=1)
    return fn


def family4() -> None:
    """Depth, size and encoding of every parsed file; unusual scenes; CARLA connection errors; interrupts."""
    deep = 100_000
    case(4, "deep-catalog", f"catalog nested {deep} deep; render", RENDER, setup=write("cat.json", deep_json(deep)), from_issue=True)
    case(4, "deep-catalog-inner", f"catalog scene 0 vehicles nested {deep} deep; drive", DRIVE, setup=chain(cp("cat.json"), edit_text("cat.json", _json_setter(["scenes", 0, "vehicles"], deep_json(deep)))))
    case(4, "deep-odd", f"ODD TOML array nested {deep} deep; evaluate --odd", f"{EVAL_HW} --odd odd.toml --out e", setup=chain(cp("hw.json"), write("odd.toml", deep_toml("name", deep))))
    case(4, "deep-odd-tables", "ODD TOML inline tables nested 50,000 deep; evaluate --odd", f"{EVAL_HW} --odd odd.toml --out e", setup=chain(cp("hw.json"), write("odd.toml", "a = " + "{b = " * 50_000 + "1" + "}" * 50_000 + "\n")))
    case(4, "deep-config", f"config TOML nested {deep} deep; corners --config", CORNERS, setup=write("c.toml", deep_toml("x", deep)))
    case(4, "deep-config-train", "config [env] value nested 100,000 deep; train --config", TRAIN, setup=write("c.toml", "[env]\n" + deep_toml("knobs", deep)))
    case(4, "deep-rulebook", f"rulebook TOML nested {deep} deep; evaluate --config", "evaluate --config rcfg.toml --catalog cat.json --policies sunny --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out e", setup=chain(cp("rcfg.toml", "cat.json"), write("rules.toml", deep_toml("rules", deep))))
    case(4, "deep-campaign", f"campaign.json nested {deep} deep; report", "report camp --out rep.html", setup=chain(CAMP, write("camp/campaign.json", deep_json(deep))))
    case(4, "deep-campaign-resume", f"campaign.json nested {deep} deep; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), write("camp/campaign.json", deep_json(deep))))
    case(4, "deep-summary", f"summary.json nested {deep} deep; report", "report camp --out rep.html", setup=chain(CAMP, write("camp/summary.json", deep_json(deep))),
         may_change=("camp/summary.json",), expect=EITHER)  # report may rebuild summary.json from the episodes
    case(4, "deep-episode-json", f"an episode JSON nested {deep} deep; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), lambda d, fx: sorted(d.glob("camp/episodes/sunny/*.json"))[0].write_text(deep_json(deep))),
         may_change=("camp/",), expect=EITHER)  # resume sets a damaged episode aside under damaged/ and runs it again
    case(4, "deep-record", f"record nested {deep} deep; replay", REPLAY, setup=write("rec.json", deep_json(deep)))
    case(4, "deep-run-config", f"the run's config.toml nested {deep} deep; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), write("run/config.toml", deep_toml("env", deep))))
    case(4, "deep-run-json", f"the run's run.json nested {deep} deep; train --resume", RESUME, setup=chain(RUN, write("run/run.json", deep_json(deep))), expect=EITHER)
    case(4, "deep-last-json", f"checkpoints/last.json nested {deep} deep; train --resume", RESUME, setup=chain(RUN, write("run/checkpoints/last.json", deep_json(deep))))
    case(4, "deep-state-json", f"the checkpoint's state.json nested {deep} deep; train --resume", RESUME, setup=chain(RUN, write("run/checkpoints/step_00000032.state.json", deep_json(deep))))
    case(4, "deep-marker", f"the campaign's .genesis-rl.json nested {deep} deep; evaluate --force onto it", f"{EVAL_HW} --out camp --force", setup=chain(CAMP, cp("hw.json"), write("camp/.genesis-rl.json", deep_json(deep))),
         may_change=("camp/",), expect=EITHER)  # its content (campaign.json) says campaign: --force replaces it, as asked
    case(4, "deep-agent-data", f"agent.zip 'data' nested {deep} deep; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), zip_member("run/agent.zip", "data", lambda d, old: deep_json(deep).encode())))
    big = 200_000
    case(4, "schedule-huge-cell", f"schedule CSV cell of {big:,} characters; drive --schedule", DRIVE + " --schedule s.csv", setup=chain(cp("cat.json"), cp("sched.csv", to="s.csv"), edit_text("s.csv", lambda t: t.replace("2,20,10", f"2,{'9' * big},10"))), from_issue=True)
    case(4, "schedule-huge-header", f"schedule CSV header cell of {big:,} characters; drive --schedule", DRIVE + " --schedule s.csv", setup=chain(cp("cat.json"), cp("sched.csv", to="s.csv"), edit_text("s.csv", lambda t: t.replace("precipitation", "p" * big, 1))))
    case(4, "schedule-unclosed-quote", "schedule CSV with an unclosed quote running to the end of the file; drive", DRIVE + " --schedule s.csv", setup=chain(cp("cat.json"), write("s.csv", 'step,fog_density\n0,"' + "1" * 300_000 + "\n")))
    case(4, "campaign-csv-huge-cell", f"the campaign's episodes.csv holds a cell of {big:,} characters; report", "report camp --out rep.html", setup=chain(CAMP, edit_text("camp/episodes.csv", lambda t: t.replace("sunny,", "sunny" + "x" * big + ",", 1))), expect=EITHER)
    case(4, "campaign-csv-huge-cell-resume", f"the campaign's episodes.csv holds a cell of {big:,} characters; evaluate --resume", RESUME_CAMP, setup=chain(CAMP, RUN, cp("hw.json"), edit_text("camp/episodes.csv", lambda t: t.replace("sunny,", '"' + "x" * big + '",', 1))), expect=EITHER)  # resume may rebuild the index from the episode files
    case(4, "run-csv-huge-cell", f"the run's episodes.csv holds a cell of {big:,} characters; train --resume", RESUME, setup=chain(RUN, lambda d, fx: (d / "run/episodes.csv").write_text((d / "run/episodes.csv").read_text() + '"' + "9" * big + '"\n')))
    case(4, "catalog-64mb", "a 64 MB catalog (one huge string field); render", RENDER, setup=chain(cp("cat.json"), edit_json("cat.json", lambda c: set_path(c, ["pad"], "x" * (64 << 20)))), expect=EITHER)
    case(4, "catalog-1gib-sparse", "a 1 GiB catalog (sparse, all NUL bytes); render", RENDER, setup=lambda d, fx: os.truncate(_touch(d / "cat.json"), 1 << 30), timeout=60)
    case(4, "schedule-1gib-sparse", "a 1 GiB schedule CSV (sparse, NUL bytes); drive --schedule", DRIVE + " --schedule s.csv", setup=chain(cp("cat.json"), lambda d, fx: os.truncate(_touch(d / "s.csv"), 1 << 30)), timeout=60)
    damaged = {"zero": lambda rel: write(rel, b""), "trunc": lambda rel: truncate(rel, 37), "binary": lambda rel: write(rel, BIN),
               "latin1": lambda rel: write(rel, LATIN1)}
    loaders = [("catalog", "cat.json", RENDER, cp("cat.json")),
               ("odd", "odd.toml", f"{EVAL_HW} --odd odd.toml --out e", cp("odd.toml", "hw.json")),
               ("config", "c.toml", "evaluate --config c.toml --catalog cat.json --policies sunny --scenes 1 --steps 5 --quiet --no-report --no-counterfactual --out e", chain(cp("tiny.toml", to="c.toml"), cp("cat.json"))),
               ("rulebook", "rules.toml", "evaluate --config rcfg.toml --catalog cat.json --policies sunny --scenes 1 --steps 5 --quiet --no-report --out e", cp("rcfg.toml", "rules.toml", "cat.json")),
               ("campaign-json", "camp/campaign.json", "report camp --out rep.html", CAMP),
               ("record", "rec.json", REPLAY, cp("rec.json")),
               ("run-config", "run/config.toml", EVAL_AGENT, chain(RUN, cp("hw.json"))),
               ("schedule", "s.csv", DRIVE + " --schedule s.csv", chain(cp("cat.json"), cp("sched.csv", to="s.csv"))),
               ("state-json", "run/checkpoints/step_00000032.state.json", RESUME, RUN),
               ("episodes-csv", "camp/episodes.csv", "report camp --out rep.html", CAMP)]  # report may rebuild this index
    for lname, rel, argv, base in loaders:
        for dname, make in damaged.items():
            case(4, f"{dname}-{lname}", f"{lname} file {rel} {dname}", argv, setup=chain(base, make(rel)),
                 expect=EITHER if lname == "episodes-csv" or (lname, dname) == ("config", "zero") else REJECT,
                 core=dname in ("zero", "binary"))  # an empty --config the user gives means the defaults
    for lname, rel, argv, base in [("agent-zip", "run/agent.zip", EVAL_AGENT, chain(RUN, cp("hw.json"))),
                                   ("checkpoint-zip", "run/checkpoints/step_00000032.zip", RESUME, RUN),
                                   ("replay-buffer", "sacrun/checkpoints/step_00000024.replay.npz", "train --out sacrun --resume --steps 36 --quiet", cp("sacrun"))]:  # .replay.pkl before 0.11.0
        for dname in ("zero", "trunc", "binary"):
            case(4, f"{dname}-{lname}", f"{lname} {rel} {dname}", argv, setup=chain(base, damaged[dname](rel)), core=dname != "trunc")
    case(4, "agent-zip-missing-data", "agent.zip without its 'data' member; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), lambda d, fx: _drop_member(d / "run/agent.zip", "data")))
    case(4, "agent-zip-policy-garbage", "agent.zip's policy.pth is garbage bytes; evaluate --agent", EVAL_AGENT, setup=chain(RUN, cp("hw.json"), zip_member("run/agent.zip", "policy.pth", lambda d, old: BIN)))
    # unusual but structurally valid scenes
    def vehicles(fn: Callable[[list[Any]], list[Any]]) -> Setup:
        return edit_json("cat.json", lambda c: set_path(c, ["scenes", 0, "vehicles"], fn(c["scenes"][0]["vehicles"])))
    case(4, "scene-ego-only", "a scene with only the ego vehicle; drive", DRIVE, setup=chain(cp("cat.json"), vehicles(lambda v: v[:1])), expect=EITHER, from_issue=True)
    case(4, "scene-ego-only-evaluate", "a scene with only the ego vehicle; evaluate", EVAL + " --out e", setup=chain(cp("cat.json"), edit_json("cat.json", _ego_only)), expect=EITHER)
    case(4, "scene-no-vehicles", "a scene with no vehicles at all; drive", DRIVE, setup=chain(cp("cat.json"), vehicles(lambda v: [])))
    case(4, "scene-two-egos", "a scene with two egos; drive", DRIVE, setup=chain(cp("cat.json"), vehicles(lambda v: [v[0], v[0]])), expect=EITHER)
    case(4, "scene-no-ego", "a scene without an ego; drive", DRIVE, setup=chain(cp("cat.json"), vehicles(lambda v: v[1:])))
    case(4, "scene-stacked-vehicles", "a scene with 60 vehicles on the same spot; drive", DRIVE, setup=chain(cp("cat.json"), vehicles(lambda v: v + [v[1]] * 60)), expect=EITHER)
    case(4, "scene-vehicles-null", "a scene whose vehicles is null; drive", DRIVE, setup=chain(cp("cat.json"), vehicles(lambda v: None)))  # type: ignore[arg-type,return-value]
    case(4, "scene-ego-autopilot", "the ego given an autopilot table; drive", DRIVE, setup=chain(cp("cat.json"), edit_json("cat.json", lambda c: set_path(c, ["scenes", 0, "vehicles", 0, "autopilot"], c["scenes"][0]["vehicles"][1]["autopilot"]))), expect=EITHER)
    case(4, "catalog-no-scenes", "a catalog whose scenes list is empty; evaluate", EVAL + " --out e", setup=chain(cp("cat.json"), edit_json("cat.json", lambda c: set_path(c, ["scenes"], []))))
    case(4, "catalog-scene-index-dup", "a catalog whose two scenes share index 0; evaluate --scenes 2", EVAL.replace("--scenes 1", "--scenes 2") + " --out e", setup=chain(cp("cat.json"), edit_json("cat.json", lambda c: set_path(c, ["scenes", 1, "index"], 0))), expect=EITHER)
    # CARLA: only loopback listeners this script runs
    for name, port in (("closed", "@PORT_closed@"), ("http", "@PORT_http@"), ("silent", "@PORT_silent@"), ("garbage", "@PORT_garbage@"), ("echo", "@PORT_echo@")):
        case(4, f"carla-port-{name}", f"--carla-port a loopback {name} server (not CARLA); scenes --backend carla", f"{CARLA} --carla-host 127.0.0.1 --carla-port {port} --carla-timeout 2", timeout=45, from_issue=name == "http")
    case(4, "carla-train-echo", "train --backend carla --carla-port an echo server", f"{TRAIN} --backend carla --carla-host 127.0.0.1 --carla-port @PORT_echo@ --carla-timeout 2", setup=cp("tiny.toml", to="c.toml"), timeout=45)
    case(4, "carla-drive-http", "drive --backend carla --carla-port an HTTP server", f"{DRIVE} --backend carla --carla-host 127.0.0.1 --carla-port @PORT_http@ --carla-timeout 2", setup=cp("cat.json"), timeout=45)
    for name, host in (("bad-ip", "256.256.256.256"), ("empty", ""), ("label-too-long", "a" * 300), ("dots", ".."), ("with-port", "127.0.0.1:2000"), ("spaces", "127.0.0.1 ; touch PWNED"), ("dash", "-h")):
        case(4, f"carla-host-{name}", f"--carla-host {host[:30]!r}", [*CARLA.split(), "--carla-host", host, "--carla-port", "@PORT_closed@", "--carla-timeout", "2"], timeout=45, core=name in ("bad-ip", "empty", "label-too-long", "with-port"))
    for name, port in (("zero", "0"), ("neg", "-1"), ("70000", "70000"), ("str", "abc"), ("empty-item", "2000,,2001"), ("float", "2000.5")):
        case(4, f"carla-port-value-{name}", f"--carla-port {port}", f"{CARLA} --carla-host 127.0.0.1 --carla-port {port} --carla-timeout 2", timeout=45, core=name in ("70000", "str", "empty-item"),
             names=(port,))  # the refusal quotes the value, not a connection failure
    for name, port in (("70000", "70000"), ("zero", "0"), ("neg", "-1"), ("str", "x")):
        case(4, f"carla-tm-port-{name}", f"--carla-tm-port {port}", f"{CARLA} --carla-host 127.0.0.1 --carla-port @PORT_closed@ --carla-tm-port {port} --carla-timeout 2", timeout=45, from_issue=name == "70000", core=name in ("70000", "str"),
             names=("tm-port", "tm_port"))
    for name, t in (("inf", "inf"), ("nan", "nan"), ("neg", "-1"), ("zero", "0"), ("huge", "1e308"), ("tiny", "1e-320"), ("str", "soon")):
        case(4, f"carla-timeout-{name}", f"--carla-timeout {t} against a silent server", f"{CARLA} --carla-host 127.0.0.1 --carla-port @PORT_silent@ --carla-timeout {t}", timeout=45, from_issue=name == "inf", core=name in ("inf", "nan", "neg", "huge"),
             names=("carla-timeout", "carla_timeout", "CARLA timeout") if name != "zero" else ())
    case(4, "carla-servers-garbage", "--carla-servers pointing at a garbage server; evaluate --backend carla", f"{EVAL} --backend carla --carla-servers 127.0.0.1:@PORT_garbage@ --carla-timeout 2 --out e", setup=cp("cat.json"), timeout=45)
    case(4, "carla-servers-malformed", "--carla-servers '127.0.0.1:x:y:z'", f"{EVAL} --backend carla --carla-servers 127.0.0.1:x:y:z --out e", setup=cp("cat.json"), timeout=45)
    # interrupts: signal the whole process group at a few moments (after the first checkpoint, while a checkpoint
    # is being written, later); the next --resume must finish the run from what was kept
    # (before the first checkpoint is complete there is nothing to resume: refusing then is right)
    moments = [("after-checkpoint", "r/checkpoints/last.json", 0.0), ("during-save", "r/checkpoints/.step_00000032.zip.*", 0.0),
               ("mid-run", "r/checkpoints/last.json", 1.5)]
    for sig, sname in ((signal.SIGINT, "sigint"), (signal.SIGTERM, "sigterm")):
        for mname, when, delay in moments:
            case(4, f"train-{sname}-{mname}", f"{sname.upper()} {mname.replace('-', ' ')} of a 96-step training, then train --resume",
                 "train --config tiny64.toml --out r --quiet", setup=cp("tiny64.toml"), signal_when=when, signal_at=delay, signal_num=sig,
                 expect=(0, 130, 143), then=["train", "--out", "r", "--resume", "--quiet"], timeout=150, from_issue=mname == "during-save")
    campaign = f"{EVAL_HW.replace('--scenes 1 --steps 5', '--scenes 3 --steps 40')} --out e"
    for sig, sname in ((signal.SIGINT, "sigint"), (signal.SIGTERM, "sigterm")):
        case(4, f"evaluate-{sname}", f"{sname.upper()} after a campaign's first episode, then the same command with --resume", campaign,
             setup=cp("hw.json"), signal_when="e/episodes/sunny/*.json", signal_at=0.2, signal_num=sig, expect=(0, 130, 143),
             then=[*campaign.split(), "--resume"], timeout=150)


def _touch(p: Path) -> Path:
    p.touch()
    return p


def _ego_only(catalog: Any) -> None:
    for scene in catalog["scenes"]:
        scene["vehicles"] = scene["vehicles"][:1]


def _drop_member(p: Path, member: str) -> None:
    with zipfile.ZipFile(p) as z:
        members = {i.filename: z.read(i.filename) for i in z.infolist() if i.filename != member}
    with zipfile.ZipFile(p, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)


def family5() -> None:
    """1e12 on every count that sets work: refused at once (the limit is generous; the case waits 20 s)."""
    T = 45.0  # "at once": before any real work; a loaded machine needs ~10 s just to start a command
    N = "1000000000000"
    bounded = [("corners-steps", f"{CORNERS} --steps {N}".replace("--steps 3 ", ""), cp("tiny.toml", to="c.toml"), True),
               ("corners-scenes", CORNERS.replace("--scenes 1", f"--scenes {N}"), cp("tiny.toml", to="c.toml"), False),
               ("evaluate-steps", f"{EVAL.replace('--steps 5', f'--steps {N}')} --out e", cp("cat.json"), False),
               ("evaluate-scenes", f"{EVAL.replace('--scenes 1', f'--scenes {N}')} --out e", cp("cat.json"), False),
               ("evaluate-search-budget-1e9", f"{EVAL.replace('sunny', 'cmaes')} --search-budget 1000000000 --out e", cp("cat.json"), True),
               ("evaluate-search-budget", f"{EVAL.replace('sunny', 'cem')} --search-budget {N} --out e", cp("cat.json"), False),
               ("evaluate-search-segments", f"{EVAL.replace('sunny', 'cmaes')} --search-segments {N} --out e", cp("cat.json"), False),
               ("evaluate-retries", f"{EVAL} --retries {N} --out e", cp("cat.json"), False),
               ("evaluate-workers", f"{EVAL} --workers {N} --out e", cp("cat.json"), False),
               ("scenes-count", f"scenes --count {N} --out c.json --quiet", None, False),
               ("render-warmup", f"{RENDER} --warmup {N}", cp("cat.json"), False),
               ("render-size", f"{RENDER} --width 1000000 --height 1000000".replace("--width 64 --height 48 ", ""), cp("cat.json"), False),
               ("drive-steps", DRIVE.replace("--steps 5", f"--steps {N}"), cp("cat.json"), False),
               ("drive-scene-range", DRIVE + f" --scene 0:{N}", cp("cat.json"), False),
               ("drive-threads", DRIVE + f" --threads {N}", cp("cat.json"), False),
               ("drive-gif-stride", DRIVE.replace("--no-gif ", "") + f" --gif-stride {N}", cp("cat.json"), False),
               ("train-steps", f"{TRAIN} --steps {N}".replace("--steps 8 ", ""), cp("tiny.toml", to="c.toml"), False),
               ("train-n-steps", f"{TRAIN} --n-steps {N}".replace("--n-steps 8 ", ""), cp("tiny.toml", to="c.toml"), False),
               ("train-episode-steps", f"{TRAIN} --episode-steps {N}", cp("tiny.toml", to="c.toml"), False),
               ("train-scenes", f"{TRAIN} --scenes {N}", cp("tiny.toml", to="c.toml"), False),
               ("config-total-timesteps", "train --config c.toml --out r --quiet", config("train", "total_timesteps", N), False),
               ("config-episode-steps", "train --config c.toml --out r --quiet", config("env", "episode_steps", N), False),
               ("config-scenes", "train --config c.toml --out r --quiet", config("env", "scenes", N), False),
               ("config-obs-size", "train --config c.toml --out r --quiet", chain(config("env", "obs_width", "100000"), edit_text("c.toml", lambda t: toml_set(t, "env", "obs_height", "100000"))), False),
               ("config-camera-size", "train --config c.toml --out r --quiet", chain(config("env", "camera_width", "1000000"), edit_text("c.toml", lambda t: toml_set(t, "env", "camera_height", "1000000"))), False),
               ("config-batch-size", "train --config c.toml --out r --quiet", config("ppo", "batch_size", N), False),
               ("config-n-epochs", "train --config c.toml --out r --quiet", config("ppo", "n_epochs", N), False),
               ("resume-steps", RESUME.replace("--steps 48", f"--steps {N}"), RUN, False),
               ("bench-system-frames-1e9", "bench system --frames 1000000000", None, True),
               ("bench-sim-steps", f"bench sim --steps {N} --frames 1 --no-render", None, False),
               ("bench-sim-frames", f"bench sim --steps 1 --frames {N}", None, False),
               ("bench-train-updates", f"bench train --updates {N} --envs 1", None, False),
               ("bench-campaign-scenes", f"bench campaign --scenes {N} --workers 1 --executors local", None, False),
               ("bench-campaign-workers-list", "bench campaign --scenes 1 --workers " + ",".join(["1"] * 30000), None, False),
               ("detector-train-frames", f"detector train --frames {N} --epochs 1 --quiet --out det", None, False),
               ("detector-train-epochs", f"detector train --frames 8 --epochs {N} --quiet --out det", None, False),
               ("detector-eval-frames", f"detector eval --frames-per-condition {N} --quiet --out de", None, False),
               ("replay-gif-seconds", f"replay rec.json --out rp --quiet --gif-seconds {N}", cp("rec.json"), False),
               ("reactivity-scenes", f"reactivity --campaign camp --policy sunny --no-other-seeds --quiet --out rx.json --scenes {N}", CAMP, False)]
    for cid, argv, setup, issue in bounded:
        expect = EITHER if cid in ("reactivity-scenes", "evaluate-workers", "drive-gif-stride", "replay-gif-seconds", "evaluate-retries", "config-batch-size") else REJECT  # batch_size is capped by n_steps
        case(5, cid, f"{cid.replace('-', ' ')} = 1e12 (or the issue's 1e9)", argv, setup=setup, timeout=T, expect=expect, from_issue=issue)


RAY_EVAL = "evaluate --catalog cat.json --policies sunny --scenes 1 --steps 5 --system blind --quiet --no-report --no-counterfactual --out e --executor ray"


def family6() -> None:
    """Ray addresses and worker counts (a lost node is tested in pytest): each answered within 20 s, in one line."""
    T = 25.0
    addresses = [("closed", "127.0.0.1:@PORT_closed@"), ("ray-closed", "ray://127.0.0.1:@PORT_closed@"),
                 ("http", "127.0.0.1:@PORT_http@"), ("silent", "127.0.0.1:@PORT_silent@"),
                 ("garbage", "127.0.0.1:@PORT_garbage@"), ("ray-silent", "ray://127.0.0.1:@PORT_silent@"),
                 ("http-scheme", "http://127.0.0.1:@PORT_http@"), ("port-70000", "127.0.0.1:70000"),
                 ("port-zero", "127.0.0.1:0"), ("port-str", "127.0.0.1:abc"), ("no-port", "127.0.0.1"),
                 ("colon", ":"), ("list", "127.0.0.1:@PORT_closed@,127.0.0.1:1"), ("bad-ip", "256.1.1.1:6379")]
    # not "auto" nor "": on a shared machine they may join someone else's cluster
    for name, addr in addresses:
        case(6, f"ray-address-{name}", f"evaluate --executor ray --ray-address {addr!r}", [*RAY_EVAL.split(), "--ray-address", addr], setup=cp("cat.json"), timeout=T, ray=True,
             core=name in ("closed", "ray-closed", "http", "silent", "garbage", "ray-silent", "port-70000", "port-str", "no-port", "colon"))
    for name, addr in (("closed", "127.0.0.1:@PORT_closed@"), ("silent", "ray://127.0.0.1:@PORT_silent@"), ("http", "127.0.0.1:@PORT_http@")):
        case(6, f"train-ray-address-{name}", f"train --envs 2 --executor ray --ray-address {addr!r}", [*TRAIN.split(), "--envs", "2", "--executor", "ray", "--ray-address", addr], setup=cp("tiny.toml", to="c.toml"), timeout=T, ray=True)
    for name, w in (("zero", "0"), ("neg", "-1"), ("empty-item", "1,,2"), ("str", "two"), ("float", "1.5"), ("huge", "1000000000000")):
        case(6, f"ray-workers-{name}", f"evaluate --executor ray --workers {w}", [*RAY_EVAL.split(), "--workers", w], setup=cp("cat.json"), timeout=T if name != "huge" else 120, ray=True, expect=EITHER if name == "huge" else REJECT, from_issue=name == "empty-item")
    for name, e in (("zero", "0"), ("neg", "-1"), ("str", "x")):
        case(6, f"train-ray-envs-{name}", f"train --executor ray --envs {e}", [*TRAIN.split(), "--envs", e, "--executor", "ray"], setup=cp("tiny.toml", to="c.toml"), timeout=T, ray=True)
    case(6, "ray-address-local-executor", "--ray-address given with --executor local", f"{EVAL} --out e --ray-address 127.0.0.1:@PORT_closed@", setup=cp("cat.json"), timeout=T, expect=EITHER)
    case(6, "ray-carla-servers-mismatch", "--executor ray --workers 2 --carla-servers with one server (lite backend)", [*RAY_EVAL.split(), "--workers", "2", "--carla-servers", "127.0.0.1:@PORT_closed@", "--ray-address", "127.0.0.1:@PORT_closed@"], setup=cp("cat.json"), timeout=T, ray=True)
    case(6, "bench-executors-bad", "bench campaign --executors ray,,local", "bench campaign --executors ray,,local --scenes 1 --workers 1", timeout=120, ray=True)
    case(6, "bench-workers-bad", "bench campaign --workers 0,-1", "bench campaign --executors local --scenes 1 --workers 0,-1", timeout=T)

if __name__ == "__main__":
    raise SystemExit(main())
