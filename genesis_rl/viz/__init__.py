"""Pictures for people: annotated camera frames, animations, plots."""
