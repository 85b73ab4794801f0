"""The rate-distortion benchmark and the shipped models."""

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from mapsqueeze.bench import run_benchmark
from mapsqueeze.cli import app
from mapsqueeze.io import write_points
from mapsqueeze.model import ModelConfig, build_model, load_model, save_model, shipped_models


@pytest.mark.slow
def test_benchmark_writes_csv_table_and_plot(tmp_path):
    rng = np.random.default_rng(0)
    ground = np.c_[rng.random((6000, 2)) * 30, rng.normal(0, 0.02, 6000)]
    wall = np.c_[rng.random(3000) * 30, np.full(3000, 5.0), rng.random(3000) * 5]
    write_points(tmp_path / "street.ply", np.vstack([ground, wall]) + [1000.0, 2000.0, 50.0])
    save_model(build_model(ModelConfig.for_rate("e0")), tmp_path / "e0")
    rows = run_benchmark([tmp_path / "street.ply"], ["octree", "mapsqueeze"], tmp_path / "out",
                         models=[str(tmp_path / "e0")], log=lambda m: None, refine=(0, 2))
    codecs = {r.codec for r in rows}
    assert codecs == {"octree", "mapsqueeze"}
    assert sorted(r.setting for r in rows if r.codec == "mapsqueeze") == ["e0,q", "e0,q+refine2"]
    octree = sorted((r for r in rows if r.codec == "octree"), key=lambda r: r.bpp)
    # coarser octrees cost fewer bits and lose more accuracy
    assert octree[0].d_e > octree[-1].d_e and octree[-1].d_e < 0.1
    with open(tmp_path / "out" / "results.csv") as f:
        assert len(list(csv.DictReader(f))) == len(rows)
    table = (tmp_path / "out" / "results.md").read_text()
    assert "| mapsqueeze |" in table
    per_cloud = [line for line in table.splitlines() if line.startswith("| street | mapsqueeze | e0,q |")]
    assert len(per_cloud) == 1 and per_cloud[0].endswith(("| yes |", "| no |", "| outside front |"))
    assert (tmp_path / "out" / "rd.png").stat().st_size > 10_000
    assert (tmp_path / "out" / "rd_street.png").stat().st_size > 10_000


@pytest.mark.slow
def test_every_nth_cloud(tmp_path):
    rng = np.random.default_rng(1)
    (tmp_path / "clouds").mkdir()
    for i in range(5):
        write_points(tmp_path / "clouds" / f"c{i}.ply", rng.random((500, 3)) * 10)
    (tmp_path / "clouds" / "c3.ply").write_bytes(b"not a cloud")  # skipped, so never read
    rows = run_benchmark([tmp_path / "clouds"], ["octree"], tmp_path / "out", log=lambda m: None, every=2)
    assert sorted({r.cloud for r in rows}) == ["c0", "c2", "c4"]


def test_bench_cli_rejects_missing_input_and_bad_refinement(tmp_path):
    result = CliRunner().invoke(app, ["bench", str(tmp_path / "nope"), "-o", str(tmp_path / "o")])
    assert result.exit_code != 0
    (tmp_path / "a.ply").write_text("")
    for refine in ("x", "-1", "", "0,20000"):
        result = CliRunner().invoke(app, ["bench", str(tmp_path / "a.ply"), "--refine", refine, "-o",
                                          str(tmp_path / "o")])
        assert result.exit_code != 0 and "refine" in str(result.exception or result.output), refine


def test_the_four_shipped_models_load_and_are_listed():
    from mapsqueeze.model.checkpoint import SHIPPED_DIR

    assert shipped_models() == ["e0", "e1", "e2", "e3"]
    for name, r_s in zip(("e0", "e1", "e2", "e3"), (3.0, 2.0, 1.2, 1.0)):
        model = load_model(name)
        assert model.config.subsampling_dist == r_s and len(model.weights_sha256) == 64
        assert (SHIPPED_DIR / name / "model.safetensors").stat().st_size < 2_000_000
        assert "## Real submaps" in (SHIPPED_DIR / name / "MODEL_CARD.md").read_text()
    result = CliRunner().invoke(app, ["models"])
    assert result.exit_code == 0 and all(name in result.output for name in ("e0", "e1", "e2", "e3"))


def test_model_labels_are_unique_path_suffixes():
    from mapsqueeze.bench import unique_labels

    assert unique_labels(["e1", "runs/x/e0"]) == ["e1", "e0"]
    assert unique_labels(["runs/a/best", "runs/b/best"]) == ["a/best", "b/best"]
    assert unique_labels(["runs/e0/best"]) == ["e0/best"]


@pytest.mark.slow
def test_benchmark_resumes_and_extends_an_earlier_run(tmp_path, monkeypatch):
    from mapsqueeze.baselines.octree import OctreeCodec

    encoded = []  # one entry per octree encoding the benchmark runs
    encode = OctreeCodec.encode
    monkeypatch.setattr(OctreeCodec, "encode", lambda self, *args: encoded.append(1) or encode(self, *args))
    rng = np.random.default_rng(1)
    write_points(tmp_path / "patch.ply", np.c_[rng.random((4000, 2)) * 20, rng.normal(0, 0.02, 4000)])
    save_model(build_model(ModelConfig.for_rate("e0")), tmp_path / "e0")
    first = run_benchmark([tmp_path / "patch.ply"], ["octree"], tmp_path / "out", log=lambda m: None)
    assert len(encoded) == len(first) > 0
    second = run_benchmark([tmp_path / "patch.ply"], ["octree", "mapsqueeze"], tmp_path / "out",
                           models=[str(tmp_path / "e0")], log=lambda m: None)
    assert second[: len(first)] == first and len(encoded) == len(first)  # kept from the CSV, not encoded again
    assert {r.codec for r in second[len(first):]} == {"mapsqueeze"}
    again = run_benchmark([tmp_path / "patch.ply"], ["octree"], tmp_path / "out", log=lambda m: None, fresh=True)
    assert len(again) == len(first) and len(encoded) == 2 * len(first)  # fresh: every octree row encoded again


def test_per_cloud_comparison_against_any_front():
    from mapsqueeze.bench import Row, per_cloud_comparison

    def row(cloud, codec, setting, bpp, d_e):
        return Row(cloud, codec, setting, 1000, int(bpp * 125), bpp, d_e, d_e / 2, 0.5, 1000, 0.1, 0.1)

    rows = [row("a", "octree", "1", 0.1, 0.4), row("a", "octree", "2", 0.4, 0.2), row("a", "draco", "x", 0.2, 0.5),
            row("a", "depoco-ref", "e0,f16", 0.1, 0.25), row("a", "depoco-ref", "e1,f16", 1.0, 0.1),
            row("a", "mapsqueeze", "e0,q", 0.2, 0.3), row("a", "mapsqueeze", "e1,q", 2.0, 0.05),
            row("b", "mapsqueeze", "e0,q", 0.2, 0.3)]
    classical = {(r.cloud, r.codec, r.setting): ref for r, ref in per_cloud_comparison(rows)}
    assert set(classical) == {("a", "depoco-ref", "e0,f16"), ("a", "depoco-ref", "e1,f16"),
                              ("a", "mapsqueeze", "e0,q"), ("a", "mapsqueeze", "e1,q"), ("b", "mapsqueeze", "e0,q")}
    assert np.isclose(classical[("a", "mapsqueeze", "e0,q")], 0.3)  # draco's (0.2, 0.5) is off the front
    assert np.isnan(classical[("a", "mapsqueeze", "e1,q")]) and np.isnan(classical[("b", "mapsqueeze", "e0,q")])
    against_reference = per_cloud_comparison(rows, ("depoco-ref",), ("mapsqueeze",))
    assert [(r.cloud, r.setting) for r, _ in against_reference] == [("a", "e0,q"), ("a", "e1,q"), ("b", "e0,q")]
    assert np.isclose(against_reference[0][1], 0.25 - 0.15 * np.log(2) / np.log(10))
    from mapsqueeze.bench import reference_comparison

    table = reference_comparison(rows)
    assert table[-3].startswith("| a | e0,q | 0.2000 | 0.3000 | 0.2048 | +46.5% | 0.2048 | +46.5% |")
    assert "outside its bpp range" in table[-2] and "outside its bpp range" in table[-1]
    assert reference_comparison([r for r in rows if r.codec != "depoco-ref"]) == []


def test_size_band_comparison_groups_clouds_by_point_count():
    from mapsqueeze.bench import Row, size_band_comparison

    def row(cloud, n_points, d_e):
        return Row(cloud, "mapsqueeze", "e1,q", n_points, 100, 0.8, d_e, d_e, 0.5, n_points, 0.1, 0.1)

    comparison = [(row("sparse", 12_000, 0.15), 0.10), (row("scan", 30_000, 0.08), 0.10),
                  (row("map_a", 90_000, 0.05), 0.10), (row("map_b", 200_000, 0.07), 0.10),
                  (row("off_front", 200_000, 0.01), float("nan"))]
    table = size_band_comparison(comparison)
    assert table[3] == "| codec | setting | 0 - 20,000 points | 20,000 - 50,000 points | >= 50,000 points |"
    assert table[5] == "| mapsqueeze | e1,q | +50.0% (0 / 1) | -20.0% (1 / 1) | -40.0% (2 / 2) |"
    assert size_band_comparison(comparison[-1:]) == []
