"""Vehicle makes and body colours: the catalog's vocabulary (a scene names a make and a colour), shared by
every backend's physics, scene generation and rendering."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Make:
    """Dimensions in metres (length along x, width, height), wheelbase, and limits of the powertrain."""

    name: str
    length: float
    width: float
    height: float
    wheelbase: float
    max_accel: float  # m/s^2 at full throttle from rest
    max_speed: float  # m/s
    weight: float  # relative frequency in scenes


MAKES: dict[str, Make] = {
    m.name: m
    for m in (
        Make("sedan", 4.6, 1.85, 1.45, 2.8, 3.5, 50.0, 0.40),
        Make("hatchback", 4.0, 1.78, 1.50, 2.5, 3.2, 45.0, 0.15),
        Make("suv", 4.8, 1.95, 1.75, 2.9, 3.2, 48.0, 0.20),
        Make("van", 5.2, 2.0, 2.2, 3.3, 2.5, 40.0, 0.10),
        Make("truck", 7.5, 2.45, 3.2, 4.6, 1.6, 33.0, 0.08),
        Make("bus", 11.0, 2.55, 3.1, 6.0, 1.4, 30.0, 0.07),
    )
}

#: Body colours drawn for scenes (sRGB 0..1): common car paints, including the hard black and grey.
PALETTE: dict[str, tuple[float, float, float]] = {
    "white": (0.92, 0.92, 0.90),
    "silver": (0.70, 0.71, 0.73),
    "grey": (0.42, 0.43, 0.45),
    "black": (0.06, 0.06, 0.07),
    "red": (0.70, 0.08, 0.08),
    "blue": (0.10, 0.22, 0.60),
    "dark_blue": (0.07, 0.10, 0.28),
    "green": (0.12, 0.38, 0.18),
    "yellow": (0.90, 0.72, 0.10),
    "orange": (0.88, 0.40, 0.08),
    "brown": (0.38, 0.24, 0.14),
    "beige": (0.78, 0.72, 0.58),
}
