"""markcal.reports."""
