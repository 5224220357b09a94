"""Design questions answered by sweeps: many simulated runs (or analyses of exact records),
one row each, in a Parquet table (docs/sweep.md).

``spec`` reads a sweep spec (TOML) into points; ``point`` computes one point's row (what a
Dask worker runs); ``engine`` runs the points missing from a table; ``table`` is the table
on disk; ``charts`` draws maps from it; ``exact`` makes the records with known truth.
"""
