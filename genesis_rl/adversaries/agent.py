"""The trained agent as an adversary, and the one place a campaign touches a training run: loading the agent
without unpickling (training/safe_load.py), checking the run's pinned files (training/pinning.py) and drawing
its learning curve for the report (training/curves.py). Campaigns, reports and the benchmark call these
functions; none of them imports ``training/``."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.adversaries.base import (
    EpisodeOutcome,
    EpisodeRunner,
    PolicyContext,
    StepPolicy,
    chooses_start,
    register_policy,
)
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.threads import pinned_threads


@register_policy
class AgentPolicy(StepPolicy):
    name = "agent"
    needs_agent = True
    reacts = True
    description = "the trained policy (PPO, SAC or a recurrent PPO), deterministic"

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        self.model = load_agent(context.agent_path)
        self.memory: Any = None  # a recurrent agent's LSTM states, carried from step to step of an episode

    def reset(self, scene: int, episode_seed: int) -> None:
        """A recurrent agent starts each episode with an empty memory, as it did in training."""
        self.memory = None

    def act(self, obs: Any) -> np.ndarray:
        with pinned_threads():  # the same floats in the main process, a pool worker or a Ray actor
            # PPO and SAC ignore state and episode_start (their memory stays None); RecurrentPPO reads and returns
            # its memory, which is None only before an episode's first step
            action, self.memory = self.model.predict(obs, state=self.memory,
                                                     episode_start=np.array([self.memory is None]), deterministic=True)
        return np.asarray(action, np.float32)

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        """An agent trained with a start head chooses its start with its first action where the campaign lets
        policies choose (``start = "natural"``); otherwise it plays from the env's start weather."""
        self.reset(scene, episode_seed)
        head = chooses_start(self.context.options) and runner.has_start_head
        return runner.run(self.act, scene, episode_seed, None, start_head=head)


def _agent_candidates(path: Path) -> list[Path]:
    return [path] if path.suffix == ".zip" else [path / "agent.zip", path / "checkpoints" / "last.zip"]


def agent_file(path: Path) -> Path | None:
    """The agent's .zip behind ``--agent``: the file itself, a run folder's agent.zip, else its last
    checkpoint; None when there is none."""
    return next((p for p in _agent_candidates(Path(path)) if p.is_file()), None)


def _run_config(agent: Path) -> Any:
    """The checked config of the run an agent file belongs to (its folder, or the folder above
    checkpoints/); None for a loose file."""
    from genesis_rl.training.config import load_run_config

    for folder in (agent.parent, agent.parent.parent):
        if (folder / "config.toml").is_file():
            try:
                return load_run_config(folder / "config.toml")
            except UserInputError as err:
                raise UserInputError(f"--agent: the run's config '{folder / 'config.toml'}': {err}") from None
    return None


def load_agent(path: Path | None) -> Any:
    """A trained agent (PPO, SAC or RecurrentPPO) from a run folder (its ``agent.zip``, else its last checkpoint)
    or a .zip file, rebuilt from its run's config.toml and the file's tensors: nothing in the file is unpickled
    (training/safe_load.py); a loose file without its run's config loads only with ``--trust-pickle``."""
    from genesis_rl.training.safe_load import load_model

    if path is None:
        raise UserInputError("policy 'agent' needs a trained agent: pass --agent runs/NAME")
    path = Path(path)
    found = agent_file(path)
    if found is None:
        candidates = _agent_candidates(path)
        raise UserInputError(f"--agent '{path}' holds no trained agent (looked for "
                             f"{', '.join(str(c) for c in candidates)}); train one with genesis-rl train")
    return load_model(found, _run_config(found), device="cpu", what="--agent")


def trained_steps(agent: Path) -> int | None:
    """The env steps an agent was trained for: a checkpoint's own (``checkpoints/step_N.zip``), else its run's
    ``train.total_timesteps``; None for a loose file without its run's config (its cost is unknown)."""
    import re

    found = agent_file(Path(agent))
    if found is None:
        return None
    named = re.fullmatch(r"step_(\d+)", found.stem)
    if named and found.parent.name == "checkpoints":
        return int(named.group(1))
    if found.name == "last.zip":  # an unfinished run: the steps its last checkpoint reached
        from genesis_rl.core.parsing import read_json

        steps = read_json(found.with_suffix(".json"), "checkpoint index").get("timesteps") \
            if found.with_suffix(".json").is_file() else None
        return steps if isinstance(steps, int) and not isinstance(steps, bool) and steps >= 0 else None
    config = _run_config(found)
    return None if config is None else int(config.train.total_timesteps)


def run_folder_of(agent: Path) -> Path:
    """The training run folder of ``--agent``: a folder, its agent.zip, or a checkpoint inside it."""
    if agent.suffix != ".zip":
        return agent
    return agent.parent.parent if agent.parent.name == "checkpoints" else agent.parent


def checked_run(agent: Path, system: str | None, weights: str | None) -> dict[str, Any]:
    """The run's config tables, once its files match the pins in its run.json (training/pinning.py): the
    agent is evaluated under the config, catalog, rulebook, ODD and detector it trained with. ``--weights``, or
    ``--system`` naming another system, replaces the run's weights on purpose: those are not checked. A run
    still being trained (its folder's lock held) is evaluated with a warning naming its last checkpoint."""
    from genesis_rl.training.pinning import check_run, last_checkpoint, read_run_config, writer_pid

    run_dir, what = run_folder_of(agent), f"--agent '{agent}'"
    run_system = read_run_config(run_dir, what)["env"].get("system", "builtin")
    replaced = weights is not None or (system is not None and system != run_system)
    data = check_run(run_dir, what, "restore it: an agent is evaluated under the files it trained with",
                     skip=("weights",) if replaced else (),
                     hints={"weights": "pass --weights FILE to evaluate the agent against other weights on purpose"})
    pid = writer_pid(run_dir)
    if pid is not None:
        last = last_checkpoint(run_dir)
        found = agent_file(agent)
        at = (f"its last checkpoint is {last[1]} (step {last[0]})" if last is not None
              else "it has no checkpoint yet")
        what_runs = f"evaluating '{found}', not the finished agent" if found else "no agent file to evaluate yet"
        print(f"genesis-rl: warning: run '{run_dir}' is still being trained (pid {pid} holds it): {at}; {what_runs}",
              file=sys.stderr, flush=True)
    return data


def agent_learning_curve(agent: Path) -> Any | None:
    """The learning-curve figure of ``agent``'s training run for a report, once the run's files in its folder
    match their pins (so the curve is the run's own); None when the run folder is not at hand."""
    from genesis_rl.training.curves import plot_learning_curve
    from genesis_rl.training.pinning import IN_FOLDER, check_run

    run = run_folder_of(Path(agent))
    if (run / "config.toml").is_file():  # the run is at hand: it is read only as it was trained
        check_run(run, f"the campaign's agent run '{run}'", "restore it, or move the run away to report "
                  "without its training curve", only=IN_FOLDER)
    return plot_learning_curve(run)
