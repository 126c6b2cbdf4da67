"""The benchmark with ground truth: falsifiers measured on the zoo's members (``genesis_rl.sut.zoo``).
It sits above ``evaluation/``: it reads and runs campaigns; campaigns do not know it."""
