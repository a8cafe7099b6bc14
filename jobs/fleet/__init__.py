"""Controller models, path rules, the registry. May import: ground floor, transports."""
