"""Adaptive Stress Testing's solver: Monte Carlo tree search over knob changes (``mcts``).

AST (Lee et al., "Adaptive Stress Testing: Finding Likely Failure Events with Reinforcement Learning", JAIR
2020) searches the disturbances of a simulation, here the knobs, for the most likely path to a failure: a tree
whose levels are the episode's decision points, grown by upper confidence bounds with progressive widening
(a node of ``n`` visits may hold ``ceil(WIDEN_C * n ** WIDEN_ALPHA)`` children, so a continuous action space
is sampled, not enumerated), each simulation one whole episode replayed from the start (lite, like AST's
seed-replay, is deterministic given the episode seed and the actions). The value of an episode is its total
reward (the agent's objective: rulebook and detector loss, as ``cmaes`` and ``cem`` maximise) plus
``search_likelihood_weight`` times its naturalness (the knob trajectory's log-likelihood ratio against held
weather, ``WeatherModel.naturalness``): AST's likelihood term, which favours the more probable of two
failures.

Levels: when the campaign lets policies choose the start (``start = "natural"``), the root chooses the held
knobs' start (uniform in [-1, 1] each: their range inside the ODD); then one level per schedule segment
(``search_segments``, as the searches'), each choosing one action per knob from {-1, 0, +1}: turn it down as
fast as nature allows, hold it, turn it up. A simulation descends by UCB1 (values scaled to [0, 1] by the
best and worst seen) until a node may widen, adds a child drawn from the scene's seeded generator, completes
the levels below at random (the rollout) and plays the episode. It spends exactly ``search_budget`` episodes
per scene and reports the best episode it played.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from genesis_rl.adversaries.base import EpisodeOutcome, EpisodeRunner, PolicyContext, SearchLedger, register_policy
from genesis_rl.adversaries.search import CMAESSearch
from genesis_rl.core.errors import UserInputError

#: a segment's action per knob: down at the natural rate, hold, up
LEVELS = np.array([-1.0, 0.0, 1.0])


@dataclass
class _Node:
    """A decision in the tree: the action that leads here, visits and the sum of the values seen below."""

    action: np.ndarray | None = None
    visits: int = 0
    total: float = 0.0
    children: list[_Node] = field(default_factory=list)


@register_policy
class TreeSearch(CMAESSearch):
    name = "mcts"
    description = ("AST's Monte Carlo tree search over knob changes (progressive widening, likelihood in the "
                   "value), search_budget episodes per scene")
    # tuned on tests/test_tree_search.py's toy schedule (20 seeds, budgets 20/40/100) among C in {1, 2, 3},
    # alpha in {0.3, 0.5}, exploration in {0.1, 0.25, 0.5, 1}: the best at 40 and near the best at 20 and 100
    WIDEN_C = 2.0
    WIDEN_ALPHA = 0.5
    EXPLORATION = 0.25  # UCB1's constant on values scaled to [0, 1]

    def __init__(self, context: PolicyContext) -> None:
        super().__init__(context)
        self.likelihood_weight = float(context.options.get("search_likelihood_weight", 1.0))
        if not (math.isfinite(self.likelihood_weight) and self.likelihood_weight >= 0.0):
            raise UserInputError(f"search_likelihood_weight = {self.likelihood_weight}: give a finite number >= 0")

    def value(self, outcome: EpisodeOutcome) -> float:
        """The episode's total reward plus the weighted naturalness (0 when the runner gave none)."""
        return outcome.total_reward + self.likelihood_weight * (outcome.naturalness or 0.0)

    def _widen(self, node: _Node) -> bool:
        return len(node.children) < math.ceil(self.WIDEN_C * (node.visits + 1) ** self.WIDEN_ALPHA)

    def run_episode(self, runner: EpisodeRunner, scene: int, episode_seed: int) -> EpisodeOutcome:
        k = self._start_dims(runner)
        rng = np.random.default_rng([self.context.seed, scene, episode_seed, 5])
        levels = ([k] if k else []) + [self.context.action_dim] * self.segments

        def draw(level: int) -> np.ndarray:
            if k and level == 0:  # the start of the held knobs: anywhere in their range
                return rng.uniform(-1.0, 1.0, k)
            return rng.choice(LEVELS, levels[level])

        root = _Node()
        low, high = math.inf, -math.inf
        values, depths, ledger = [], [], SearchLedger()
        for _ in range(self.budget):
            node, path = root, list[_Node]()
            while len(path) < len(levels):  # selection, then one expansion
                if self._widen(node):
                    child = _Node(draw(len(path)))
                    node.children.append(child)
                    path.append(child)
                    break
                span = max(high - low, 1e-9)
                log_n = math.log(node.visits)
                node = max(node.children, key=lambda c: (c.total / c.visits - low) / span
                           + self.EXPLORATION * math.sqrt(log_n / c.visits))
                path.append(node)
            depths.append(len(path))
            chosen = [c.action for c in path if c.action is not None]
            actions = chosen + [draw(level) for level in range(len(path), len(levels))]  # the rollout
            x = np.concatenate(actions[1:] + actions[:1]) if k else np.concatenate(actions)  # start entries last
            outcome = self._play(runner, x, scene, episode_seed, k)
            v = ledger.add(outcome, self.value(outcome))
            values.append(round(v, 3))
            low, high = min(low, v), max(high, v)
            root.visits += 1
            for c in path:  # backpropagation
                c.visits += 1
                c.total += v
        return ledger.report(search_values=values, tree_depths=depths, root_children=len(root.children))
