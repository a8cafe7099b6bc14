"""Who may do what: users, named API keys, roles, and the audit trail of what they did."""
