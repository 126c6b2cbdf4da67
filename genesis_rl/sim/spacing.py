"""The route and lane sample spacing every backend shares: the controller's route holds a point every
``DS`` metres whichever simulator drew it, so it lives outside both backends."""

from __future__ import annotations

DS = 0.5  # lane sample spacing [m]
