"""Cooperative safety applications (pure library code: no I/O, no clocks)."""
