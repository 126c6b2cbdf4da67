"""GENESIS-RL: natural edge cases for autonomous driving, found by an RL agent that turns the weather."""

__version__ = "0.29.0"
