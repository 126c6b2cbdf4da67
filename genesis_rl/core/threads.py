"""One thread policy for the system under test's arithmetic.

A CPU kernel's floats can depend on how many threads split its reductions: on some CPUs (AMD EPYC among them)
a convolution on one thread and on two rounds differently in the last bits. The process that plays an episode
may be the main one (torch's default threads), a pool worker, a Ray actor or a resumed run, so the detector and
the adversary's policy pin their own thread count for each call instead of inheriting the process's. The same
seed then gives the same floats in every mode on any one machine.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

#: threads for every forward pass of the system under test and of a learned adversary during an episode
INFERENCE_THREADS = 1


@contextmanager
def pinned_threads(threads: int = INFERENCE_THREADS) -> Iterator[None]:
    """Run the block with exactly ``threads`` torch threads, then give the process its own setting back."""
    import torch

    before = torch.get_num_threads()
    if before != threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)
