"""Rate-distortion benchmark: every codec and setting on every cloud -> results.csv, run.json, results.md, plots.

clouds (what to run on), variants (codecs x settings: the learned codecs through the same compress/decompress
calls as the CLI, the classical ones from the baselines registry), runner (the loop, resumption, run.json),
fronts (per-metric Pareto fronts and comparisons at equal bpp), report (markdown), plots (PNG).
"""

from mapsqueeze.benchmark.rows import Row
from mapsqueeze.benchmark.runner import run_benchmark

__all__ = ["Row", "run_benchmark"]
