"""Test-session settings. ``scripts/test.sh`` runs the suite on two pytest-xdist workers (``--dist loadgroup``):
tests that start their own local Ray instance, drive CARLA fakes on fixed ports, or time signals against a
running process share a group, so each group runs on one worker, one test at a time."""

from __future__ import annotations

import pytest

#: test module name prefix -> xdist group
GROUPS = {"test_ray": "ray", "test_carla": "carla", "test_interrupts": "signals",
          "test_benchmark_command": "benchmark"}  # one module-scoped matrix, built once


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        module = item.module.__name__.rpartition(".")[2] if item.module else ""
        for prefix, group in GROUPS.items():
            if module.startswith(prefix):
                item.add_marker(pytest.mark.xdist_group(group))
