"""Scenes from Scenic 3, the paper's scene generator (``genesis-rl scenes --generator scenic``).

Its own package because it reads both kinds of map (lite and CARLA) and writes the shared catalog schema:
it sits above ``lite``, ``carla_backend`` and ``scenes`` and none of them imports it.
"""
