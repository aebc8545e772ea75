"""Evaluation protocols shared by the toolkit's evaluators (numpy only)."""
