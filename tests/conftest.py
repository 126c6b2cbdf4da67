"""Test-session settings. ``scripts/test.sh`` runs the suite on two pytest-xdist workers (``--dist loadgroup``):
tests that start their own local Ray instance, drive CARLA fakes on fixed ports, or time signals against a
running process share a group, so each group runs on one worker, one test at a time. Modules whose expensive
artefact (a benchmark, two campaigns, a hardened detector) is a session fixture are grouped too, so that one
worker builds it once.

Each worker computes with one torch thread (and so do the commands it starts, through ``OMP_NUM_THREADS``):
two workers on two cores with torch's default of two threads each would only contend for the cores. Tests of
thread counts set their own.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

#: test module name prefix -> xdist group
GROUPS = {"test_ray": "ray", "test_carla": "carla", "test_interrupts": "signals",
          "test_benchmark_command": "benchmark", "test_compare": "compare", "test_harden": "harden"}


def pytest_configure(config: pytest.Config) -> None:
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        import torch

        torch.set_num_threads(1)


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook writes the groups into the test ids
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        module = item.module.__name__.rpartition(".")[2] if item.module else ""
        for prefix, group in GROUPS.items():
            if module.startswith(prefix):
                item.add_marker(pytest.mark.xdist_group(group))



#: a run, a campaign and records written by genesis-rl 0.29.0 (tests/data/genesis_rl_0.29.0/README.md)
V029 = Path(__file__).parent / "data" / "genesis_rl_0.29.0"


@pytest.fixture()
def v029(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of the 0.29.0 run (``run/``) and campaign (``camp/``) to change, the working folder set to it:
    the campaign names its agent and catalog relative to where it ran."""
    shutil.copytree(V029, tmp_path / "old")
    monkeypatch.chdir(tmp_path / "old")
    return tmp_path / "old"
