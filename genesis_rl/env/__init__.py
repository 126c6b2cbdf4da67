"""The GENESIS-RL Gymnasium environment, registered as ``genesis_rl/Weather-v0``."""

import gymnasium

from genesis_rl.env.genesis_env import ENV_ID, EnvConfig, GenesisEnv

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="genesis_rl.env.genesis_env:GenesisEnv", max_episode_steps=None)

__all__ = ["ENV_ID", "EnvConfig", "GenesisEnv"]
