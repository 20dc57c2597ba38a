"""Evaluation: how good a map, a route or a set of parameters is (docs/architecture.md §4–§5).

metrics.py        the ground-truth metric, tag RMSE and the shift metric
ground_truth.py   RTAB-Map exports and the ground-truth JSON form
table.py          one row of the evaluation table (pre-optimized vs optimized vs truth)
tuning.py         search spaces, trials, the grid and a sampler (sweep_plan.py: their order)
simulate/         synthetic sessions with known truth (simulate_building.py: several walks)
turn_metrics.py   announced turns against a reference corridor graph
"""
