"""How often would it fail? Failure-rate estimates under a nominal model of the world.

Data flow: :mod:`nominal` says what natural driving draws (the start of the knobs that an episode cannot move,
the per-step weather noise); :mod:`proposal` tilts the start toward failures (a cross-entropy-adapted mixture
with a defensive share of nominal starts); :mod:`episodes` plays one drawn episode and says whether it failed
inside the ODD; :mod:`estimator` turns the weighted outcomes into an estimate with its interval, its effective
sample size and the failure clusters that carry it; :mod:`run` drives stages, workers, checkpoints and files.
"""
