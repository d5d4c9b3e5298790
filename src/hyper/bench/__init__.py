"""Benchmarks: ``python -m hyper.bench <name>``; each writes results/bench/<name>.json and charts.

Speeds are reported as ratios of methods timed side by side in one run, so a loaded
or slower machine changes the absolute numbers but not the conclusions.
"""
