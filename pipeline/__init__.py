"""markcal.pipeline."""
