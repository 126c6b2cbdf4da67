"""Upper bounds on sizes and counts that would otherwise exhaust memory or run for days.

Each limit is generous for real use (the paper's sizes are far below it) and can be raised for one run by
an environment variable, which the error message names: ``GENESIS_RL_MAX_SCENES=500000 genesis-rl scenes ...``.
Measured on 2 CPU cores: generating a lite scene takes about 50 ms, a lite simulation tick about 3.4 ms.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from genesis_rl.core.errors import UserInputError


@dataclass(frozen=True)
class Limit:
    name: str  # the environment variable's suffix: GENESIS_RL_MAX_<name>
    default: int
    unit: str
    cost: str  # what the default costs, so the user can judge raising it

    @property
    def variable(self) -> str:
        return f"GENESIS_RL_MAX_{self.name}"

    def value(self) -> int:
        text = os.environ.get(self.variable)
        if text is None:
            return self.default
        try:
            value = int(text)
        except ValueError:
            raise UserInputError(f"{self.variable} = '{text}' must be an integer") from None
        if value < 1:
            raise UserInputError(f"{self.variable} = {value} must be >= 1")
        return value

    def check(self, value: int, field: str, given: str | None = None) -> None:
        """Refuse ``value`` (of the flag or config key ``field``, spelt ``given`` by the user) above the limit,
        saying how to raise it."""
        limit = self.value()
        if value > limit:
            shown = f"{field} {given!r} needs {value:,} {self.unit}" if given else f"{field} = {value:,}"
            raise UserInputError(f"{shown}, over the limit of {limit:,} {self.unit} ({self.cost}); set "
                                 f"{self.variable} to raise it")


SCENES = Limit("SCENES", 100_000, "scenes", "generating that many takes about 80 minutes")
SIM_STEPS = Limit("SIM_STEPS", 100_000, "simulation steps", "83 simulated minutes, about 6 minutes to run")
TIMESTEPS = Limit("TIMESTEPS", 100_000_000, "env steps", "the paper trains 40,960; this many takes over a year "
                                                          "at 3 steps/s")
SEARCH_BUDGET = Limit("SEARCH_BUDGET", 1_000, "episodes a scene", "the paper's searches spend 8; 1,000 on 50 scenes "
                                                                  "of 512 steps is 50,000 episodes, about 5 days")
FRAMES = Limit("FRAMES", 100_000, "frames", "rendering and detecting that many takes about half an hour; a detector "
                                            "training set of that many 320x240 frames holds 23 GB")
EPOCHS = Limit("EPOCHS", 1_000, "epochs", "the shipped detector trains 20")
WORKERS = Limit("WORKERS", 256, "processes", "each runs a simulator and takes a CPU core and about 1 GB of memory")
THREADS = Limit("THREADS", 256, "threads", "more threads than cores only slow a run down")
BUFFER = Limit("BUFFER", 1_000_000, "transitions", "held in memory: 1,000,000 camera observations of 72x96 take "
                                                   "21 GB; the paper's PPO holds 2,048")
ROUNDS = Limit("ROUNDS", 100, "rounds", "the paper hardens in 3; each attacks, retrains and re-tests, minutes to hours")
RETRIES = Limit("RETRIES", 100, "retries", "each reconnects to the simulator and plays the episode again")


#: the most items a comma list of counts may have (--workers 1,2,4,8 names four runs)
MAX_LIST_ITEMS = 16


def count_list(text: str | None, flag: str, limit: Limit, least: int = 1) -> tuple[int, ...]:
    """A comma list of counts (``--workers 1,2,4``): every item an integer in ``least``..the limit, none empty
    (``1,,2`` is a typo, not the list 1,2)."""
    items = [t.strip() for t in (text or "").split(",")]
    try:
        counts = tuple(int(t) for t in items)
    except ValueError:
        counts = ()
    if not counts or min(counts) < least:
        raise UserInputError(f"{flag} {text!r}; allowed: a comma list of integers >= {least}, e.g. 1,2 (no empty "
                             "items)")
    if len(counts) > MAX_LIST_ITEMS:  # each item is a whole run (bench campaign times one campaign per item)
        raise UserInputError(f"{flag} lists {len(counts):,} counts; allowed: at most {MAX_LIST_ITEMS} (each one is a "
                             "separate run)")
    for c in counts:
        limit.check(c, flag, text)
    return counts
