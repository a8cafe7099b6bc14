"""Drip-feed runs: restart points, modal state, run records."""
