"""A weather policy whose worker process dies the first time it plays one scene: it stands for a Ray worker
lost mid-episode (a node gone, an out-of-memory kill). The marker file says the crash already happened."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from genesis_rl.adversaries import StepPolicy, register_policy

#: folder of the marker files (set by the test); the scene whose first episode kills its worker
MARKERS = "GENESIS_RL_TEST_CRASH_DIR"
CRASH_SCENE = "GENESIS_RL_TEST_CRASH_SCENE"


@register_policy
class CrashOnce(StepPolicy):
    """Sunny weather; the first episode on scene $GENESIS_RL_TEST_CRASH_SCENE kills its process at step 10."""

    name = "crash_once"

    def reset(self, scene: int, episode_seed: int) -> None:
        self.steps = 0
        self.crash = False
        folder = os.environ.get(MARKERS)
        if folder and str(scene) == os.environ.get(CRASH_SCENE):
            marker = Path(folder) / f"crashed_{scene}"
            if not marker.exists():
                marker.write_text("1")
                self.crash = True

    def act(self, obs):
        self.steps += 1
        if self.crash and self.steps == 10:
            os._exit(1)  # no cleanup, no exception: the process is gone
        return np.zeros(self.context.action_dim, np.float32)
