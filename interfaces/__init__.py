"""What users touch: the ``cosim5g`` CLI, the REST API with its results pages and token auth, the
API's run store and the HTTP client. Runs go through the coordinator, sweeps through the
experiments engine."""
