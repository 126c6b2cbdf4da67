"""The catalogs a process generated or read are kept by what determines them: the same key gives the same
scenes without the cost, and an edited catalog file is read afresh."""

from __future__ import annotations

from genesis_rl.sim.backends import load_catalog
from genesis_rl.sim.lite.scenes import generate_catalog, iter_scenes


def test_a_generated_catalog_is_kept_by_map_count_seed_and_traffic() -> None:
    a = generate_catalog("urban", 3, seed=11)
    assert generate_catalog("urban", 3, seed=11) is a  # kept
    assert a.scenes == tuple(iter_scenes("urban", 3, 11))  # and the same scenes as generating them afresh
    assert generate_catalog("urban", 3, seed=12).scenes != a.scenes
    assert len(generate_catalog("urban", 2, seed=11).scenes) == 2
    free = generate_catalog("highway", 2, seed=11, traffic="free_flow")
    mixed = generate_catalog("highway", 2, seed=11)
    assert free is not mixed and free.scenes != mixed.scenes


def test_a_catalog_file_is_kept_by_its_content(tmp_path) -> None:
    path = tmp_path / "c.json"
    generate_catalog("urban", 2, seed=5).save(path)
    first = load_catalog(path)
    assert load_catalog(path) is first
    copy = tmp_path / "copy.json"
    copy.write_bytes(path.read_bytes())
    assert load_catalog(copy) is first  # the same bytes elsewhere
    generate_catalog("urban", 2, seed=6).save(path)  # edited in place: read again
    again = load_catalog(path)
    assert again is not first and again.seed == 6 and again.scenes == generate_catalog("urban", 2, seed=6).scenes
