"""Scene catalogs: the versioned JSON schema of initial scenes and its vocabulary (vehicle makes, colours).

It imports no simulator: each backend's scene module (``genesis_rl.lite.scenes``,
``genesis_rl.carla_backend.scenes``) generates catalogs and checks them against its maps, and
``genesis_rl.backends.load_catalog`` runs those checks when a catalog is loaded.
"""
