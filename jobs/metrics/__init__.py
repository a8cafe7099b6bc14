"""The fleet's figures for Prometheus: read from the database at scrape time (`figures`),
exposed as metric families by one collector (`collector`).

The workers are other processes, so nothing is counted in memory where the work is done:
every scrape of the API's `/metrics` reads the record that every process writes.
"""
