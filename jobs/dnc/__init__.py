"""Drip-feed runs: restart points, modal state, run records. May import: jobs.rollout and below."""
