"""Does this CPU round the detector's arithmetic differently at different torch thread counts?

The mechanism behind "one worker and two compute different floats": a convolution split over more threads can
round differently. For the built-in detector on random frames, this prints the CPU, then for each process
thread count the largest difference of the net's raw outputs from one thread when the thread count is left to
the process (unpinned), and whether the detections are bit-identical to one thread's when the detector pins its
own threads (``genesis_rl.core.threads``, what every run does). Runs on the CPU alone.

    .venv/bin/python scripts/thread_floats.py [--threads 1,2,4,8] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path


def cpu_name() -> str:
    """The CPU's vendor and model, from /proc/cpuinfo where there is one."""
    fields: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    except OSError:
        return platform.processor() or "unknown"
    return f"{fields.get('vendor_id', '?')} {fields.get('model name', '?')}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", default="1,2,4", help="process thread counts to compare (default: 1,2,4)")
    parser.add_argument("--frames", type=int, default=3, help="random 320x240 frames (default: 3)")
    parser.add_argument("--json", default=None, help="also write the result as JSON here")
    args = parser.parse_args()
    counts = [int(t) for t in args.threads.split(",")]

    import numpy as np
    import torch

    from genesis_rl.sut.perception.detector import VehicleDetector

    frames = np.random.default_rng(0).integers(0, 256, (args.frames, 240, 320, 3), dtype=np.uint8)
    det = VehicleDetector(score_threshold=1e-5, max_detections=400)
    iw, ih = det.input_size
    import cv2

    small = np.stack([cv2.resize(f, (iw, ih), interpolation=cv2.INTER_AREA) for f in frames])
    x = torch.from_numpy(det._normalized(small)).permute(0, 3, 1, 2)
    raw: dict[int, list[np.ndarray]] = {}
    pinned: dict[int, list[bytes]] = {}
    for n in counts:
        torch.set_num_threads(n)
        with torch.inference_mode():
            out = det._forward(x)  # the process's own thread count: what a worker did before the pin
        raw[n] = [v.detach().numpy().copy() for _, v in sorted(out.items())]
        pinned[n] = [d.tobytes() for d in det.detect_batch(frames)]
    base = counts[0]
    rows = []
    for n in counts:
        diff = max(float(np.max(np.abs(a - b))) for a, b in zip(raw[n], raw[base], strict=True))
        rows.append({"threads": n, "unpinned_max_abs_diff": diff, "pinned_identical": pinned[n] == pinned[base]})
    result = {"cpu": cpu_name(), "cores": os.cpu_count(), "torch": torch.__version__,
              "reference_threads": base, "rows": rows}
    print(f"cpu: {result['cpu']}; torch {torch.__version__}")
    print(f"{'threads':>8} {'unpinned: max |raw - raw@' + str(base) + '|':>32} {'pinned: detections identical':>30}")
    for r in rows:
        print(f"{r['threads']:>8} {r['unpinned_max_abs_diff']:>32.3g} {str(r['pinned_identical']):>30}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0 if all(r["pinned_identical"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
