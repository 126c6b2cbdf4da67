"""How long a process spends on catalogs: one 1,199-scene highway catalog generated twice, then saved and read
three times, as a campaign's preparation and its episodes do (docs/benchmarks.md). Run it from the checkout to
measure, e.g. ``python scripts/catalog_cache_speed.py after``; the argument labels the line it prints."""

import sys
import tempfile
import time

t0 = time.perf_counter()
from genesis_rl.sim.backends import load_catalog  # noqa: E402  (the imports are part of what is timed)
from genesis_rl.sim.lite.scenes import generate_catalog  # noqa: E402


def timed(fn, *args):
    start = time.perf_counter()
    value = fn(*args)
    return value, time.perf_counter() - start


catalog, gen = timed(generate_catalog, "highway", 1199, 0)
_, gen2 = timed(generate_catalog, "highway", 1199, 0)
with tempfile.TemporaryDirectory() as tmp:
    path = f"{tmp}/catalog.json"
    catalog.save(path)
    loads = [timed(load_catalog, path)[1] for _ in range(3)]
label = sys.argv[1] if len(sys.argv) > 1 else "catalogs"
print(f"{label}: generate {gen:.1f} s, again {gen2:.2f} s, loads " + ", ".join(f"{x:.2f}" for x in loads) + " s; "
      f"total {time.perf_counter() - t0:.1f} s")
