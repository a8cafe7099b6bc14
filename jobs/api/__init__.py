"""The HTTP API (the contract's /api/cnc and dncq's own). May import: all but cli, worker."""
