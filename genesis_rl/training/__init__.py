"""Training the adversarial weather agent with Stable-Baselines3 PPO on the paper's schedule."""
