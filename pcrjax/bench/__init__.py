"""Benchmarks: `pcrjax bench` (cases, driver, kernel counts)."""
