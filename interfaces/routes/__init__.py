"""The REST API's routers, one per resource: runs, sweeps, and the site (pages, login, docs,
metrics, health)."""
