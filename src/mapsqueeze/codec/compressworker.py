"""Imported by the server that compress's worker processes are forked from (`compress.WORKER_MODULES`): numba's
compiler starts here once, with one cached kernel loaded, so that every worker starts with it ready instead of
starting it itself (~1 CPU-s a process; its memory is shared with the server, BENCHMARKS.md "Throughput")."""

import numpy as np

from mapsqueeze.model.influences import bias_leaky_relu

bias_leaky_relu(np.zeros((1, 1), dtype=np.float32), np.zeros(1, dtype=np.float32), np.float32(0.01))
