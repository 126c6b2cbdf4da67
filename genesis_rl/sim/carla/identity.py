"""A CARLA map's identity: the SHA-256 of its OpenDRIVE text, not its name.

``client.generate_opendrive_world`` names every world it makes "OpenDriveMap", whatever the roads: a name
says nothing about which export is loaded. A catalog made on a server stores the digest of the map it was
made on (``map_digest``), and an episode checks the loaded map against it before spawning.
"""

from __future__ import annotations

import hashlib


def opendrive_digest(xodr: str) -> str:
    """SHA-256 (hex) of the map's OpenDRIVE text as the server returns it (``carla.Map.to_opendrive``)."""
    return hashlib.sha256(xodr.encode("utf-8")).hexdigest()


def short(digest: str) -> str:
    return digest[:12]
