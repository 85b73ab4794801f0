"""Same input, model and flags give byte-identical files whatever the thread count (`set_threads`: the compiled
kernels' and torch's), every time.

A shipped model on a synthetic 40 m tile: with MKL splitting its matrix products by thread count, e0's f32 bytes
differed between 1 and 2 threads (and e0 f16 on the real KITTI submap), and refined files now and then between runs;
the numpy forward's products run on one BLAS thread for the same reason.
"""

import numpy as np
import pytest
import torch
from threadpoolctl import ThreadpoolController

import mapsqueeze
from mapsqueeze.geometry.threads import set_threads, threads
from mapsqueeze.model import load_model

BLAS = ThreadpoolController()
"""numpy's BLAS threads, which the caller may set too."""


@pytest.fixture(scope="module")
def tile_points():
    rng = np.random.default_rng(0)
    n = 30_000
    ground = np.column_stack([rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.normal(0.5, 0.05, n)])
    wall = np.column_stack([rng.uniform(0, 40, n // 3), rng.normal(20, 0.05, n // 3), rng.uniform(0.5, 8, n // 3)])
    return np.concatenate([ground, wall]) + [500_000.0, 4_000_000.0, 50.0]


@pytest.fixture
def restore_threads():
    previous = threads(), torch.get_num_threads()
    yield
    set_threads(previous[0])
    torch.set_num_threads(previous[1])


@pytest.mark.parametrize("precision, refine_steps, repeats", [("f32", 0, 2), ("f16", 0, 2), ("q", 0, 2),
                                                              ("f16", 2, 2)])
def test_bytes_do_not_depend_on_the_thread_count(tile_points, restore_threads, precision, refine_steps, repeats):
    model = load_model("e0")
    files = set()
    for _ in range(repeats):
        for count in (1, 2):
            set_threads(count)
            with BLAS.limit(limits=count, user_api="blas"):
                files.add(mapsqueeze.compress(tile_points, model=model, precision=precision,
                                              refine_steps=refine_steps))
    assert len(files) == 1
    assert threads() == 2 and torch.get_num_threads() == 2  # the caller's setting is restored


def test_decoded_points_do_not_depend_on_the_thread_count(tile_points, restore_threads):
    model = load_model("e0")
    data = mapsqueeze.compress(tile_points, model=model, precision="f32")
    decoded = []
    for count in (1, 2):
        set_threads(count)
        with BLAS.limit(limits=count, user_api="blas"):
            decoded.append(mapsqueeze.decompress(data, model=model).tobytes())
    assert decoded[0] == decoded[1]
