"""Offscreen rendering for the lite backend: Panda3D geometry pass, then a numpy/OpenCV weather pass."""
