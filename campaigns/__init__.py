"""Fitting campaigns over many materials (scripts; run from the repository root)."""
