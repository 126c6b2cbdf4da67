"""GENESIS-RL: natural edge cases for autonomous driving, found by an RL agent that turns the weather.

The package is laid out by its data flow, each layer importing only from those before it:
core -> world -> sim, distributed -> sut -> loop -> env, labels -> training -> adversaries -> campaigns ->
analysis, exports -> benchmark, estimation, harden -> commands (docs/architecture.md).
"""

from genesis_rl import compat as _compat

__version__ = "0.30.0"

_compat.install()
