"""Drip-feed runs: restart points, modal state, run records. May import: jobs.service and below."""
