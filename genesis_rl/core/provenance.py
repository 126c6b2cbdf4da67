"""Where a result came from: the git commit of the code that made it (recorded in runs and campaigns)."""

from __future__ import annotations

import subprocess
from pathlib import Path


def git_commit() -> str:
    """The commit of the package's checkout, or "unknown" outside a git checkout (an installed wheel)."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def numeric_platform() -> dict[str, str]:
    """What an episode's floating-point results depend on besides the code and the seed: the CPU's vector
    extensions numpy and torch dispatch to, and their versions. Two machines that agree here replay an
    episode bit for bit; across others (AVX2 against AVX-512, say) vector math differs in the last bits, the
    violations agree to ~1e-9 and a rare detection score may not (docs/scaling.md, "Results")."""
    import platform

    import numpy as np
    import torch

    try:  # numpy's own runtime report (np.show_runtime) reads the same
        from numpy._core._multiarray_umath import (  # type: ignore[import-not-found]
            __cpu_dispatch__,
            __cpu_features__,
        )

        simd = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
        numpy_simd = simd[-1] if simd else "baseline"
    except ImportError:  # pragma: no cover - another numpy layout
        numpy_simd = "unknown"
    return {"machine": platform.machine(), "numpy_simd": numpy_simd, "numpy": np.__version__,
            "torch_cpu": torch.backends.cpu.get_cpu_capability(), "torch": torch.__version__.split("+")[0]}
