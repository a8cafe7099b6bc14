"""The HTTP API: the contract's `/api/cnc/...` contract and dncq's own admin and job routes."""
