"""What a campaign is: the policies, the held-out scenes and their seeds, and the env they play under.

The paper's testing protocol: scenes picked from the test catalog by the campaign seed, each with an
episode seed drawn from it, so NPC appearance and paths are identical across policies; 512 steps each.
Everything here is checked before a folder is touched.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from genesis_rl.adversaries import PolicyContext, checked_run, load_agent, resolve_policy, run_folder_of
from genesis_rl.adversaries.replay import OPTION as SCHEDULES
from genesis_rl.adversaries.replay import build_policy, schedules_option
from genesis_rl.core.config import read_toml
from genesis_rl.core.errors import UserInputError
from genesis_rl.core.plugins import check_import
from genesis_rl.world.knobs import PAPER_KNOBS


@dataclass(frozen=True)
class CampaignSpec:
    """Everything that decides a campaign's results (``workers`` does not)."""

    policies: tuple[str, ...]
    map: str = "highway"
    catalog: str | None = None  # test catalog file; None: generate the map's default catalog
    catalog_seed: int = 0
    scenes: int = 50
    seed: int = 0
    steps: int = 512
    agent: str | None = None  # run folder or .zip of the trained agent
    env: dict[str, Any] = field(default_factory=dict)  # EnvConfig fields (from the agent's run)
    options: dict[str, Any] = field(default_factory=dict)  # policy options (search_budget, ...)
    records: str = "failures"  # edge-case records for: failures (collision or proximity violation), all
    frames_before: int = 40  # steps of camera frames kept before the first collision
    frames_after: int = 6
    frame_stride: int = 2
    #: the generated catalog's traffic (genesis_rl.world.scenes.placement.TRAFFIC): mixed (the paper's) or free_flow;
    #: written to campaign.json only when not mixed, so campaigns written before read the same
    traffic: str = "mixed"
    #: scene indices never drawn (a benchmark's tuning scenes keep out of its held-out ones); written to
    #: campaign.json only when given, so campaigns written before read the same
    exclude: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        """The counts that set a campaign's work, bounded also when they come from a campaign.json."""
        from genesis_rl.core import limits

        for name, limit in (("steps", limits.SIM_STEPS), ("scenes", limits.SCENES)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise UserInputError(f"campaign spec.{name} = {value!r}; allowed: an integer >= 1")
            limit.check(value, f"campaign spec.{name}")  # the lower bound: where the scenes are picked and run
        from genesis_rl.adversaries import chooses_start
        from genesis_rl.world.scenes.placement import TRAFFIC

        if self.traffic not in TRAFFIC:
            raise UserInputError(f"campaign spec.traffic = {self.traffic!r}; allowed: {', '.join(TRAFFIC)}")
        if self.traffic != "mixed" and self.catalog:
            raise UserInputError(f"campaign spec.traffic = '{self.traffic}' generates its scenes, and a catalog file "
                                 f"('{self.catalog}') brings its own: pass one or the other")
        if not isinstance(self.exclude, tuple) or not all(
                isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in self.exclude) \
                or len(set(self.exclude)) != len(self.exclude):
            raise UserInputError(f"campaign spec.exclude = {self.exclude!r}; allowed: distinct scene indices >= 0")
        chooses_start(self.options)  # a bad options.start is refused here, before any episode runs
        for name, limit in (("search_budget", limits.SEARCH_BUDGET), ("retries", limits.RETRIES)):
            value = self.options.get(name)
            if isinstance(value, int) and not isinstance(value, bool):
                limit.check(value, f"campaign spec.options.{name}")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["policies"] = list(self.policies)
        if self.traffic == "mixed":
            del d["traffic"]
        if self.exclude:
            d["exclude"] = list(self.exclude)
        else:
            del d["exclude"]
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> CampaignSpec:
        """The spec that :meth:`to_json` wrote (campaign.json's ``spec``)."""
        exclude = d.get("exclude", ())
        return cls(**{**d, "policies": tuple(d["policies"]),
                      "exclude": tuple(exclude) if isinstance(exclude, list) else exclude})

    def policy_context(self, action_dim: int) -> PolicyContext:
        """What this campaign's policies are built from."""
        return PolicyContext(action_dim=action_dim, seed=self.seed, agent_path=Path(self.agent) if self.agent else None,
                             options={**self.options, "steps": self.steps})


def pick_scenes(n_catalog: int, count: int, seed: int, exclude: tuple[int, ...] = ()) -> list[tuple[int, int]]:
    """(scene index, episode seed) pairs: ``count`` distinct scenes drawn by ``seed``, in catalog order, none of
    ``exclude`` (without it, the draw of every version before)."""
    allowed = n_catalog - len({i for i in exclude if i < n_catalog})
    if not 1 <= count <= allowed:
        raise UserInputError(f"--scenes = {count} must be in 1..{allowed} (the test catalog's size"
                             + (f", less {n_catalog - allowed} excluded scenes)" if exclude else ")"))
    # numpy draws from an index array as from its length, so without exclude this is the draw of before
    pool = np.setdiff1d(np.arange(n_catalog), np.asarray(exclude, dtype=np.int64))
    indices = sorted(int(i) for i in np.random.default_rng(seed).choice(pool, size=count, replace=False))
    return [(i, int(np.random.default_rng([seed, i]).integers(0, 2**31 - 1))) for i in indices]


def campaign_map(map_flag: str | None, catalog: str | None) -> str:
    """The campaign's map: the test catalog's (``--map``, when given as well, must name it: a campaign records
    its map, and a catalog of one map run under another's name would record the wrong one), else ``--map``,
    else highway."""
    if not catalog:
        return map_flag or "highway"
    from genesis_rl.world.scenes.catalog import read_catalog

    found = read_catalog(catalog).map
    if map_flag is not None and map_flag != found:
        raise UserInputError(f"--map {map_flag} and --catalog '{catalog}' disagree: the catalog's scenes are on map "
                             f"'{found}'; pass --map {found} (or leave --map out), or a catalog made for map "
                             f"'{map_flag}' (genesis-rl scenes --map {map_flag})")
    return found


def env_settings_for(agent: str | None, config: str | None, system: str | None,
                     weights: str | None = None) -> dict[str, Any]:
    """The env settings policies play under: the trained agent's own (so its observation matches), else a
    config file's [env], else the defaults; ``system`` overrides the system under test (and drops the
    settings of the one it replaces), ``weights`` its detector's weights."""
    env: dict[str, Any] = {}
    if agent:
        run = Path(agent)
        run_dir = run_folder_of(run)
        cfg_path = run_dir / "config.toml"
        if not run.exists():
            raise UserInputError(f"--agent '{agent}' does not exist")
        if not cfg_path.is_file():
            raise UserInputError(f"--agent '{agent}': no config.toml in '{run_dir}', so its env settings are unknown")
        env = dict(checked_run(run, system, weights)["env"])
    elif config:
        env = dict(read_toml(config).get("env", {}))
    if system and system != env.get("system", "builtin"):
        env["system"] = system
        env.pop("system_kwargs", None)
    if weights is not None:
        from genesis_rl.sut.system.protocol import WEIGHTED_SYSTEMS

        if env.get("system", "builtin") not in WEIGHTED_SYSTEMS:
            raise UserInputError(f"--weights applies to --system {', '.join(WEIGHTED_SYSTEMS)} only, not "
                                 f"'{env.get('system')}'")
        if env.get("system") == "coco":
            if not Path(weights).is_dir():
                raise UserInputError(f"--weights '{weights}' is not a folder (coco takes the folder holding "
                                     f"yolov3-tiny.cfg, yolov3-tiny.weights and coco.names)")
        elif not Path(weights).is_file():
            raise UserInputError(f"--weights '{weights}' is not a file")
        env["system_kwargs"] = {**env.get("system_kwargs", {}), "weights": str(weights)}
    for key in ("catalog", "scenes", "catalog_seed", "map", "episode_steps", "start_spread", "start_bonus",
                "start_bonus_cells"):
        env.pop(key, None)  # the campaign decides these (and every test episode starts at start_weather)
    env["terminate_on_collision"] = False  # the protocol drives every episode for its full length
    return env


def check_spec(spec: CampaignSpec) -> None:
    """Everything that can be checked before a folder is touched: policies, their options, the agent."""
    if spec.steps < 1:
        raise UserInputError(f"--steps = {spec.steps} must be >= 1")
    if spec.records not in ("failures", "all"):
        raise UserInputError(f"records = '{spec.records}' is unknown; allowed: failures, all")
    plugins = spec.env.get("plugins") or ()
    for name in [plugins] if isinstance(plugins, str) else plugins:  # imported by every worker: checked here
        check_import(str(name), "env.plugins")
    for name in spec.policies:
        cls = resolve_policy(name)
        if cls.needs_agent and not spec.agent:
            raise UserInputError(f"policy '{name}' needs a trained agent: pass --agent runs/NAME")
        if not cls.needs_agent:
            action_dim = len(spec.env.get("knobs") or PAPER_KNOBS)
            build_policy(cls, name, spec.policy_context(action_dim))  # a bad schedule is refused here too
    strangers = sorted(set(schedules_option(spec.options)) - set(spec.policies))
    if strangers:
        raise UserInputError(f"campaign option {SCHEDULES} names {strangers}, which the campaign does not play; "
                             f"allowed: {', '.join(spec.policies)}")
    if any(resolve_policy(p).needs_agent for p in spec.policies):
        load_agent(Path(spec.agent) if spec.agent else None)
