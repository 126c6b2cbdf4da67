"""Scene catalogs: the versioned JSON schema of initial scenes and its vocabulary (vehicle makes, colours).

It imports no simulator: each backend's scene module (``genesis_rl.sim.lite.scenes``,
``genesis_rl.sim.carla.scenes``) generates catalogs and checks them against its maps, and
``genesis_rl.sim.backends.load_catalog`` runs those checks when a catalog is loaded.
"""
