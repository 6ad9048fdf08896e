"""The experiment layer: sweeps over scenario fields and seeds, and what they conclude.

spec (what to sweep) -> points (one resolved scenario + seed each, keyed by a hash) -> executor
(local processes or a Ray cluster) -> records (one row per run, per-loop rows) -> summary (mean and
95% CI over seeds), capacity (largest load meeting a success threshold), figures and report. The
CLI, the REST API and the policy evaluation all run sweeps through this one engine.
"""
