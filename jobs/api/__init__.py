"""The HTTP API: the contract's `/api/cnc/...` routes and dncq's own admin and job routes."""
