"""Harden a system on the failures found: attack, retrain its detector on the failure frames, re-test, in rounds
(``genesis-rl harden``, docs/harden.md)."""
