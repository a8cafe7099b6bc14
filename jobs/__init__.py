"""dncq control plane: what was asked of the fleet and what happened."""

__version__ = "0.1.0"
# Every answer of dncq's API carries its version in this header: the CLI tells dncq's
# answers from another server's by it (an API's JSON of another shape would not do).
VERSION_HEADER = "X-Dncq-Version"
