"""Same input, model and flags give byte-identical files whatever torch's thread count, every time.

A shipped model on a synthetic 40 m tile: with MKL splitting its matrix products by thread count, e0's f32 bytes
differed between 1 and 2 threads (and e0 f16 on the real KITTI submap), and refined files now and then between runs.
"""

import numpy as np
import pytest
import torch

import mapsqueeze
from mapsqueeze.model import load_model


@pytest.fixture(scope="module")
def tile_points():
    rng = np.random.default_rng(0)
    n = 30_000
    ground = np.column_stack([rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.normal(0.5, 0.05, n)])
    wall = np.column_stack([rng.uniform(0, 40, n // 3), rng.normal(20, 0.05, n // 3), rng.uniform(0.5, 8, n // 3)])
    return np.concatenate([ground, wall]) + [500_000.0, 4_000_000.0, 50.0]


@pytest.fixture
def restore_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("precision, refine_steps, repeats", [("f32", 0, 2), ("f16", 0, 2), ("q", 0, 2),
                                                              ("f16", 2, 2)])
def test_bytes_do_not_depend_on_the_thread_count(tile_points, restore_threads, precision, refine_steps, repeats):
    model = load_model("e0")
    files = set()
    for _ in range(repeats):
        for threads in (1, 2):
            torch.set_num_threads(threads)
            files.add(mapsqueeze.compress(tile_points, model=model, precision=precision, refine_steps=refine_steps))
    assert len(files) == 1
    assert torch.get_num_threads() == 2  # the caller's setting is restored


def test_decoded_points_do_not_depend_on_the_thread_count(tile_points, restore_threads):
    model = load_model("e0")
    data = mapsqueeze.compress(tile_points, model=model, precision="f32")
    decoded = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        decoded.append(mapsqueeze.decompress(data, model=model).tobytes())
    assert decoded[0] == decoded[1]
