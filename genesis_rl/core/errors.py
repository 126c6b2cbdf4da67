"""One error type for bad user input: the CLI prints its message and exits with status 2, no traceback."""

from __future__ import annotations


class UserInputError(ValueError):
    """Bad input from a user (a flag, a file, a config value). The message names the field and what is allowed."""

    exit_code = 2


class SimulatorLost(RuntimeError):
    """The simulator stopped answering during an episode (e.g. a CARLA server died). The episode is lost but
    nothing recorded is: a campaign reconnects and retries it."""
