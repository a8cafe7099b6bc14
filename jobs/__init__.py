"""dncq control plane: what was asked of the fleet and what happened."""

__version__ = "0.1.0"
