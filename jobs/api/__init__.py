"""The HTTP API: the seed's `/api/cnc/...` contract and dncq's own admin and job routes."""
