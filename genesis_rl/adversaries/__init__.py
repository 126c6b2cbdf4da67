"""The adversaries: who turns the knobs while the system under test drives, behind one interface
(``base.WeatherPolicy``), found by name (``resolve_policy``).

- ``base``: the interface, the episode runner a policy plays through, the registry;
- ``step``: ``sunny``, ``random`` (natural rates), ``constant`` (an open-loop schedule);
- ``search``: ``cmaes`` and ``cem`` over piecewise-constant schedules, ``random_search`` (random at their budget),
  ``corner_search`` (the best corner of the action box);
- ``tree``: ``mcts``, Adaptive Stress Testing's Monte Carlo tree search over knob changes;
- ``goexplore``: Go-Explore, an archive of cells returned to from exact snapshots (lite only);
- ``verifai_search``: ``verifai_ce``, ``verifai_mab``, ``verifai_bo``, VerifAI's own samplers (the ``verifai`` extra);
- ``scripted``: ``stall_watcher`` and ``fixed_onset``, a reactive member's ground truth (react, or not);
- ``agent``: the trained policy, and the only module that reads a training run.

Campaigns (``evaluation/``) and the benchmark (``benchmark/``) import adversaries from here.
"""

# isort: off
# registration order is the order users read in --help and errors: the step policies, the agent, the searches
from genesis_rl.adversaries.base import (
    POLICIES,
    STARTS,
    EpisodeOutcome,
    EpisodeRunner,
    ExploringRunner,
    PolicyContext,
    StepPolicy,
    WeatherPolicy,
    chooses_start,
    register_policy,
    resolve_policy,
)
from genesis_rl.adversaries.step import ConstantPolicy, RandomPolicy, SunnyPolicy
from genesis_rl.adversaries.agent import (
    AgentPolicy,
    agent_file,
    agent_learning_curve,
    checked_run,
    load_agent,
    run_folder_of,
)
from genesis_rl.adversaries.search import CMAESSearch, CornerSearch, CrossEntropySearch, RandomSearch
from genesis_rl.adversaries.tree import TreeSearch
from genesis_rl.adversaries.goexplore import GoExplore
from genesis_rl.adversaries.scripted import FixedOnset, StallWatcher
from genesis_rl.adversaries.verifai_search import VerifaiBandit, VerifaiBayesOpt, VerifaiCrossEntropy
# isort: on

__all__ = ["AgentPolicy", "CMAESSearch", "ConstantPolicy", "CornerSearch", "CrossEntropySearch", "EpisodeOutcome",
           "EpisodeRunner", "ExploringRunner", "GoExplore",
           "FixedOnset", "StallWatcher", "VerifaiBandit", "VerifaiBayesOpt", "VerifaiCrossEntropy",
           "POLICIES", "PolicyContext", "RandomPolicy", "RandomSearch", "STARTS", "StepPolicy", "SunnyPolicy",
           "TreeSearch", "WeatherPolicy", "agent_file", "agent_learning_curve", "checked_run", "chooses_start",
           "load_agent", "register_policy", "resolve_policy", "run_folder_of"]
