"""Queue, leases, the runners' transactions, recovery. May import: jobs.fleet and below."""
