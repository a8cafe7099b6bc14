"""Streamed and stored backups, ZIPs, retention. May import: jobs.service and below."""
