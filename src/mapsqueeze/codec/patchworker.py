"""Imported by the server that decompress's worker processes are forked from when a file's tiles use patch planes
(`decompress.PATCH_WORKER_MODULES`): numba starts here once, with the patch-plane kernel loaded from its cache, so
that every worker starts with it ready instead of loading it itself (~1 CPU-s a process; its memory is shared with
the server, BENCHMARKS.md "Throughput")."""

import numpy as np

from mapsqueeze.geometry.patches import patch_planes

patch_planes(np.zeros((1, 3)), 1, 0.7, 1, 0.05, np.ones(3))
