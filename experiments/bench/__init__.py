"""Parts of experiments/benchmark.py: the cases (cases), the timer (timing),
the per-part profile (profile) and the report (report).  benchmark.py parses
its arguments and sets XLA flags before any of these import JAX."""
