"""PNG plots with matplotlib's Agg backend: a map seen from above, and a sweep's heat maps."""
