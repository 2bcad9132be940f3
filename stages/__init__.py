"""markcal.stages."""
