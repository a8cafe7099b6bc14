"""dncq data plane: everything that touches a machine."""
