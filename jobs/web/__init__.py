"""The web dashboard: server-rendered pages at `/` of the API's server, over the services."""
