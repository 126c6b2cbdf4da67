"""Procedural vehicle models: extents match the makes, every vertex carries the label in alpha."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("panda3d")

from panda3d.core import GeomVertexReader, NodePath  # noqa: E402

from genesis_rl.sim.lite.render.vehicle_models import VehicleModel, build_vehicle_model  # noqa: E402
from genesis_rl.world.scenes.vehicles import MAKES, PALETTE  # noqa: E402


def _vertices(vm: VehicleModel) -> tuple[np.ndarray, np.ndarray]:
    """Positions (in the root frame) and colours of all vehicle geoms, shadow excluded."""
    pos, col = [], []
    for path in vm.root.find_all_matches("**/+GeomNode"):
        if path == vm.shadow:
            continue
        mat = path.get_mat(vm.root)
        for geom in path.node().get_geoms():
            vdata = geom.get_vertex_data()
            rv, rc = GeomVertexReader(vdata, "vertex"), GeomVertexReader(vdata, "color")
            while not rv.is_at_end():
                p = mat.xform_point(rv.get_data3())
                pos.append((p[0], p[1], p[2]))
                col.append(tuple(rc.get_data4()))
    return np.array(pos), np.array(col)


@pytest.mark.parametrize("make", sorted(MAKES))
def test_extents_match_make(make: str) -> None:
    mk = MAKES[make]
    pos, _ = _vertices(build_vehicle_model(make, PALETTE["red"], 40))
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    assert lo[2] == pytest.approx(0.0, abs=0.02)
    assert hi[2] - lo[2] == pytest.approx(mk.height, rel=0.03)
    assert hi[1] - lo[1] == pytest.approx(mk.length, rel=0.03)
    # mirrors may stick out sideways; the body itself (below the mirrors) must match the width
    body = pos[pos[:, 2] < 0.8]
    assert body[:, 0].max() - body[:, 0].min() == pytest.approx(mk.width, rel=0.03)
    assert hi[0] - lo[0] < mk.width * 1.2
    assert abs(hi[0] + lo[0]) < 0.02 and abs(hi[1] + lo[1]) < 0.05  # centred


@pytest.mark.parametrize("make", sorted(MAKES))
@pytest.mark.parametrize("label", [32, 77, 254])
def test_every_vertex_alpha_is_label(make: str, label: int) -> None:
    vm = build_vehicle_model(make, PALETTE["black"], label)
    for lights, braking in ((False, False), (True, False), (False, True), (True, True)):
        vm.set_lights(lights, braking)
        _, col = _vertices(vm)
        assert len(col) > 0
        assert np.all(np.rint(col[:, 3] * 255) == label)
        # a flat colour set on a lamp node must carry the label too
        for part in (vm.headlights, vm.taillights):
            if part.has_color():
                assert round(part.get_color()[3] * 255) == label


@pytest.mark.parametrize("make", sorted(MAKES))
def test_triangle_budget_and_shadow(make: str) -> None:
    vm = build_vehicle_model(make, (0.5, 0.5, 0.5), 33)
    assert 100 < vm.num_triangles < 600
    assert not vm.root.find("**/shadow").is_empty()
    vm.set_shadow(1.0, -2.0, 0.0)
    assert vm.shadow.is_hidden()
    vm.set_shadow(1.0, -2.0, 0.8)
    assert not vm.shadow.is_hidden()
    lo, hi = vm.shadow.get_tight_bounds(vm.root)
    assert hi[2] < 0.05 and lo[0] < -MAKES[make].width / 2 and hi[0] > MAKES[make].width / 2 + 0.9


def test_unknown_make_and_bad_label() -> None:
    with pytest.raises(KeyError):
        build_vehicle_model("tank", (1, 1, 1), 40)
    with pytest.raises(ValueError):
        build_vehicle_model("sedan", (1, 1, 1), 256)
    assert isinstance(build_vehicle_model("sedan", (1, 1, 1), 40).root, NodePath)
