"""The inbox: programs machines sent that were not requests, held for review."""
