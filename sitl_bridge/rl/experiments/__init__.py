"""Experiments across seeds: sweeps, the experiment runner, RESULTS.md (report, results
and its sections), backend transfer and the report's caches."""
