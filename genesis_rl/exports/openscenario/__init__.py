"""Failures as ASAM OpenSCENARIO scenarios (docs/openscenario.md).

Data flow: an edge-case record -> ``trace`` (lite replays it; every vehicle's path) -> ``writer`` (a .xosc
beside the map's .xodr, through scenariogeneration) -> ``schema`` (ASAM's XSD) -> ``reader`` (the file read
back by scenariogeneration's reader) -> ``lite_replay`` (lite driven from the parsed file). ``environment`` is
the knob <-> Environment mapping both ways; ``export`` runs the chain for a campaign's failures.
Needs the ``openscenario`` extra (scenariogeneration, lxml).
"""
