"""Evaluation: campaigns of weather policies on held-out scenes, their statistics, failure modes,
edge-case records and replay, reports and dataset export."""
