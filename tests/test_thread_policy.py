"""The system under test computes the same floats whatever thread count its process runs with.

On some CPUs a convolution rounds differently on one thread and on two; on this project's Intel machines
the detector's raw outputs already differ in the last bits between 1 and 2-8 process threads. The detector
pins its own threads per call (``genesis_rl.core.threads``), so the main process (torch's default threads),
a pool worker (one thread) and a Ray actor compute the same detections.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from genesis_rl.core.threads import INFERENCE_THREADS, pinned_threads


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def _frames() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (3, 240, 320, 3), dtype=np.uint8)


def test_detections_are_bit_identical_at_1_2_and_4_process_threads(restore_threads) -> None:
    from genesis_rl.sut.perception.detector import VehicleDetector

    # a threshold this low keeps hundreds of raw scores, so a last-bit difference in the net would show
    det = VehicleDetector(score_threshold=1e-5, max_detections=400)
    frames = _frames()
    outs = {}
    for threads in (1, 2, 4):
        torch.set_num_threads(threads)
        outs[threads] = det.detect_batch(frames)
        assert torch.get_num_threads() == threads  # the process's own setting survives the call
    assert sum(len(d) for d in outs[1]) > 100
    for threads in (2, 4):
        for a, b in zip(outs[1], outs[threads], strict=True):
            assert a.tobytes() == b.tobytes(), f"detections at {threads} process threads differ from 1 thread"


def test_pinned_threads_restores_the_process_setting(restore_threads) -> None:
    torch.set_num_threads(3)
    with pinned_threads():
        assert torch.get_num_threads() == INFERENCE_THREADS
    assert torch.get_num_threads() == 3
    with pytest.raises(RuntimeError), pinned_threads(2):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == 3
