"""Per-pixel labels, written by the geometry pass into the framebuffer's alpha channel.

Every surface is drawn opaque with its label as alpha (label / 255), so one render gives the colour,
a semantic map, and per-vehicle instance masks for occlusion-aware ground-truth boxes.
"""

SKY = 0
GROUND = 1  # grass, terrain, open ground
ROAD = 2
LANE_MARKING = 3
SIDEWALK = 4
BUILDING = 5
VEGETATION = 6
POLE = 7  # traffic lights, street lamps, guard rails
PUDDLE = 8

#: vehicle i of a scene has label VEHICLE_BASE + i
VEHICLE_BASE = 32
MAX_VEHICLES = 255 - VEHICLE_BASE

ROADLIKE = (ROAD, LANE_MARKING, PUDDLE)

NAMES = {
    SKY: "sky",
    GROUND: "ground",
    ROAD: "road",
    LANE_MARKING: "lane_marking",
    SIDEWALK: "sidewalk",
    BUILDING: "building",
    VEGETATION: "vegetation",
    POLE: "pole",
    PUDDLE: "puddle",
}


def vehicle_label(index: int) -> int:
    if not 0 <= index < MAX_VEHICLES:
        raise ValueError(f"vehicle index {index} out of 0..{MAX_VEHICLES - 1}")
    return VEHICLE_BASE + index


def alpha(label: int) -> float:
    """The alpha value (0..1) that encodes ``label`` exactly in an 8-bit channel."""
    return label / 255.0
