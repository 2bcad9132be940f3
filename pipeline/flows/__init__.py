"""markcal.pipeline.flows."""
