"""The experiment layer: sweeps over scenario fields and seeds, and what they conclude.

spec -> points (a resolved scenario + seed each, keyed by a hash) -> executor -> records ->
summary, capacity, figures and report; one engine for the CLI, the REST API and policy evaluation.
"""
