"""The ``carla`` backend: GENESIS-RL against a real CARLA 0.9.16 server through the ``carla`` client package.

Importing this package needs nothing; its modules import ``carla`` through :func:`require_carla`, which fails
with the install command when the optional extra is missing. Entry points:

- :class:`genesis_rl.sim.carla.backend.CarlaBackend` (the :class:`~genesis_rl.sim.interface.Backend`),
- :func:`genesis_rl.sim.carla.scenes.generate_catalog_from_server` (scene catalogs on CARLA maps).
"""

from genesis_rl.sim.carla._carla import INSTALL_HINT, require_carla

__all__ = ["INSTALL_HINT", "require_carla"]
