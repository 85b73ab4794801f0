"""The rate-distortion benchmark and the shipped models."""

import csv
import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import mapsqueeze
from mapsqueeze.benchmark import Row, run_benchmark
from mapsqueeze.cli.commands import load_commands
from mapsqueeze.io import write_points
from mapsqueeze.model import ModelConfig, build_model, load_model, save_model, shipped_models

app = load_commands()  # every command


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
    per_cloud = [line for line in table.splitlines() if line.startswith("| street | 9,000 | mapsqueeze | e0,q |")]
    assert len(per_cloud) == 1 and per_cloud[0].endswith(("D_e wins, IoU wins |", "D_e wins, IoU loses |",
                                                          "D_e loses, IoU wins |", "D_e loses, IoU loses |",
                                                          "outside the front's bpp range |"))
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
    from mapsqueeze.model.shipped import SHIPPED_DIR

    assert shipped_models() == ["e0", "e1", "e2", "e3"]
    for name, r_s in zip(("e0", "e1", "e2", "e3"), (3.0, 2.0, 1.2, 1.0)):
        model = load_model(name)
        assert model.config.subsampling_dist == r_s and len(model.weights_sha256) == 64
        assert (SHIPPED_DIR / name / "model.safetensors").stat().st_size < 2_000_000
        assert "## Real submaps" in (SHIPPED_DIR / name / "MODEL_CARD.md").read_text()
    result = CliRunner().invoke(app, ["models"])
    assert result.exit_code == 0 and all(name in result.output for name in ("e0", "e1", "e2", "e3"))


def test_model_labels_are_unique_path_suffixes():
    from mapsqueeze.benchmark.variants import unique_labels

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


def _row(cloud, codec, setting, bpp, d_e, iou=0.5, n_points=1000):
    return Row(cloud, codec, setting, "", n_points, int(bpp * n_points / 8), bpp, d_e, d_e / 2, iou, n_points, 0.1,
               0.1)


def test_comparison_against_any_front_per_metric():
    from mapsqueeze.benchmark.fronts import compare

    rows = [_row("a", "octree", "1", 0.1, 0.4, iou=0.2), _row("a", "octree", "2", 0.4, 0.2, iou=0.3),
            _row("a", "draco", "x", 0.2, 0.5, iou=0.6),
            _row("a", "depoco-ref", "e0,f16", 0.1, 0.25), _row("a", "depoco-ref", "e1,f16", 1.0, 0.1),
            _row("a", "mapsqueeze", "e0,q", 0.2, 0.3), _row("a", "mapsqueeze", "e1,q", 2.0, 0.05),
            _row("b", "mapsqueeze", "e0,q", 0.2, 0.3)]
    classical = {c.row.key(): c for c in compare(rows)}
    assert set(classical) == {("a", "depoco-ref", "e0,f16"), ("a", "depoco-ref", "e1,f16"),
                              ("a", "mapsqueeze", "e0,q"), ("a", "mapsqueeze", "e1,q"), ("b", "mapsqueeze", "e0,q")}
    at_02 = classical[("a", "mapsqueeze", "e0,q")]
    assert np.isclose(at_02.front["d_e"], 0.3)  # draco's (0.2, 0.5) is off the D_e front
    assert np.isclose(at_02.front["iou"], 0.6)  # ... and on the IoU front, where higher is better
    assert np.isclose(at_02.ratio("d_e"), 1.0)
    assert np.isclose(at_02.difference("iou"), -0.1) and not at_02.wins("iou")
    assert not classical[("a", "mapsqueeze", "e1,q")].within_range()
    assert not classical[("b", "mapsqueeze", "e0,q")].within_range()
    against_reference = compare(rows, ("depoco-ref",), ("mapsqueeze",))
    assert [(c.row.cloud, c.row.setting) for c in against_reference] == [("a", "e0,q"), ("a", "e1,q"), ("b", "e0,q")]
    assert np.isclose(against_reference[0].front["d_e"], 0.25 - 0.15 * np.log(2) / np.log(10))
    from mapsqueeze.benchmark.report import reference_comparison

    table = reference_comparison(rows)
    assert table[-3].startswith("| a | e0,q | 0.2000 | 0.3000 | 0.2048 | +46.5% | 0.2048 | +46.5% |")
    assert "outside its bpp range" in table[-2] and "outside its bpp range" in table[-1]
    assert reference_comparison([r for r in rows if r.codec != "depoco-ref"]) == []


def test_the_classical_front_is_every_registered_baseline(monkeypatch, tmp_path):
    """A codec added to the baselines registry joins the front, and its points are scored in the cloud's frame."""
    from mapsqueeze.baselines import BASELINES
    from mapsqueeze.baselines.base import BaselineCodec
    from mapsqueeze.benchmark.fronts import classical_codecs, compare

    class Lossless(BaselineCodec):
        name = "lossless"

        def settings(self):
            return [{"copy": 1}]

        def encode(self, points, setting):
            return np.asarray(points, dtype="<f8").tobytes()

        def decode(self, data):
            return np.frombuffer(data, dtype="<f8").reshape(-1, 3)

    monkeypatch.setitem(BASELINES, "lossless", Lossless)
    assert "lossless" in classical_codecs() and "gpcc" in classical_codecs()
    write_points(tmp_path / "far.ply", np.random.default_rng(0).random((300, 3)) * 10 + [5e5, 4e6, 100.0])
    rows = run_benchmark([tmp_path / "far.ply"], ["lossless"], tmp_path / "out", log=lambda m: None)
    assert rows[0].d_e < 1e-6 and rows[0].iou == 1.0  # decoded points put back at the cloud's origin
    learned = _row("far", "mapsqueeze", "e0,q", rows[0].bpp, 0.1)
    assert np.isclose(compare(rows + [learned])[0].front["d_e"], rows[0].d_e)


def test_report_states_wins_losses_and_the_target_per_cloud():
    from mapsqueeze.benchmark.report import markdown_report

    rows = [_row("map", "gpcc", "mode=trisoup,cell_m=0.1,node_log2=3", 0.1, 0.10, iou=0.40, n_points=100_000),
            _row("map", "gpcc", "mode=trisoup,cell_m=0.1,node_log2=2", 0.4, 0.05, iou=0.60, n_points=100_000),
            _row("map", "mapsqueeze", "e0,q", 0.1, 0.07, iou=0.45, n_points=100_000),
            _row("map", "mapsqueeze", "e2,q", 0.4, 0.045, iou=0.5, n_points=100_000)]
    lines = markdown_report(rows).splitlines()
    e0 = next(line for line in lines if line.startswith("| map | 100,000 | mapsqueeze | e0,q |"))
    assert "| 0.1000 | 0.0700 | 0.1000 | 0.700 |" in e0 and "| +0.050 |" in e0
    assert e0.endswith("| D_e wins, IoU wins; target met |")
    e2 = next(line for line in lines if line.startswith("| map | 100,000 | mapsqueeze | e2,q |"))
    assert "| 0.900 |" in e2 and e2.endswith("| D_e wins, IoU loses; target missed |")
    wins = [line for line in lines if line.startswith("| mapsqueeze | e0,q | 1 / 1 |")]
    assert len(wins) == 1 and wins[0].endswith("| 0.700 | +0.050 | 1 / 1 |")
    assert "| map | 100,000 | mapsqueeze | **0.100: 0.70 / +0.05** | 0.400: 0.90 / -0.10 |" in lines


def test_report_names_the_codecs_of_a_partial_front():
    """A run of fewer classical codecs is compared with the front of those, and the report says which ran: not
    "the full classical front" of codecs that never ran."""
    from mapsqueeze.benchmark.fronts import classical_codecs
    from mapsqueeze.benchmark.report import markdown_report

    rows = [_row("map", "octree", "leaf_m=0.4", 0.1, 0.10, iou=0.40), _row("map", "octree", "leaf_m=0.2", 0.4, 0.05),
            _row("map", "mapsqueeze", "e1,q", 0.2, 0.07, iou=0.45)]
    report = markdown_report(rows)
    not_run = ", ".join(codec for codec in classical_codecs() if codec != "octree")
    assert "full classical front" not in report
    assert report.count(f"the classical front of octree only ({not_run} not run)") == 3
    assert report.count("the classical front of") == 3
    every = [_row("map", codec, "x", 0.3, 0.2) for codec in classical_codecs()]
    assert markdown_report(rows + every).count(f"the full classical front ({', '.join(classical_codecs())})") == 3
    learned_only = markdown_report([rows[-1]])
    assert learned_only.count(f"a classical front (none ran of {', '.join(classical_codecs())})") == 3
    park = [_row("park", codec, "x", 0.3, 0.2) for codec in classical_codecs() if codec != "gpcc"]
    park.append(_row("park", "mapsqueeze", "e1,q", 0.2, 0.07))
    gpcc_not_on_park = markdown_report(rows + every + park)  # every codec ran, but not every codec on every cloud
    assert "full classical front" not in gpcc_not_on_park
    assert gpcc_not_on_park.count(f"the classical front of {', '.join(classical_codecs())}; gpcc not run on park") == 3
    assert "not run on" not in markdown_report(rows + every)


def test_size_band_comparison_groups_clouds_by_point_count():
    from mapsqueeze.benchmark.fronts import Comparison
    from mapsqueeze.benchmark.report import size_band_comparison

    def compared(cloud, n_points, d_e, front):
        return Comparison(_row(cloud, "mapsqueeze", "e1,q", 0.8, d_e, n_points=n_points),
                          {"d_e": front, "d_perp": front, "iou": 0.5})

    comparison = [compared("sparse", 12_000, 0.15, 0.10), compared("scan", 30_000, 0.08, 0.10),
                  compared("map_a", 90_000, 0.05, 0.10), compared("map_b", 200_000, 0.07, 0.10),
                  compared("off_front", 200_000, 0.01, float("nan"))]
    table = size_band_comparison(comparison)
    assert table[3] == "| codec | setting | 0 - 20,000 points | 20,000 - 50,000 points | >= 50,000 points |"
    assert table[5] == "| mapsqueeze | e1,q | +50.0% (0 / 1) | -20.0% (1 / 1) | -40.0% (2 / 2) |"
    assert size_band_comparison(comparison[-1:]) == []


@pytest.mark.slow
def test_resumed_run_reruns_rows_of_retrained_weights_and_records_them(tmp_path):
    rng = np.random.default_rng(2)
    write_points(tmp_path / "patch.ply", np.c_[rng.random((3000, 2)) * 20, rng.normal(0, 0.02, 3000)])
    save_model(build_model(ModelConfig.for_rate("e0")), tmp_path / "e0")
    first = run_benchmark([tmp_path / "patch.ply"], ["octree", "mapsqueeze"], tmp_path / "out",
                          models=[str(tmp_path / "e0")], log=lambda m: None)
    old_hash = load_model(str(tmp_path / "e0")).weights_sha256
    assert {r.weights for r in first if r.codec == "mapsqueeze"} == {old_hash}
    assert {r.weights for r in first if r.codec == "octree"} == {""}
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    assert record["model_weights_sha256"] == {"mapsqueeze:e0": old_hash}
    assert record["arguments"]["codecs"] == ["octree", "mapsqueeze"] and record["version"] == mapsqueeze.__version__
    retrained = build_model(ModelConfig.for_rate("e0"))
    with torch.no_grad():
        next(retrained.parameters()).add_(0.01)
    save_model(retrained, tmp_path / "e0")  # retrained: same name, other weights
    messages = []
    second = run_benchmark([tmp_path / "patch.ply"], ["octree", "mapsqueeze"], tmp_path / "out",
                           models=[str(tmp_path / "e0")], log=messages.append)
    new_hash = load_model(str(tmp_path / "e0")).weights_sha256
    assert new_hash != old_hash and any("other model weights" in m for m in messages)
    assert [r for r in second if r.codec == "octree"] == [r for r in first if r.codec == "octree"]
    assert {r.weights for r in second if r.codec == "mapsqueeze"} == {new_hash}
    assert json.loads((tmp_path / "out" / "run.json").read_text())["model_weights_sha256"] == {"mapsqueeze:e0": new_hash}


def test_bench_cli_rejects_unknown_codecs_before_running(tmp_path):
    write_points(tmp_path / "a.ply", np.random.default_rng(0).random((100, 3)))
    for codecs in ("octree,gpc", "", " , "):
        result = CliRunner().invoke(app, ["bench", str(tmp_path / "a.ply"), "--codecs", codecs, "-o",
                                          str(tmp_path / "o")])
        assert result.exit_code != 0 and "--codecs" in str(result.exception), codecs
        assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_bench_runs_real_gpcc_octree_and_trisoup(tmc3, tmp_path):
    rng = np.random.default_rng(4)
    ground = np.c_[rng.random((8000, 2)) * 30, rng.normal(0, 0.02, 8000)]
    wall = np.c_[rng.random(4000) * 30, np.full(4000, 5.0), rng.random(4000) * 5]
    write_points(tmp_path / "street.ply", np.vstack([ground, wall]) + [3e5, 5e6, 40.0])
    result = CliRunner().invoke(app, ["bench", str(tmp_path / "street.ply"), "--codecs", "gpcc,octree", "-o",
                                      str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    from mapsqueeze.benchmark.rows import read_rows

    rows = read_rows(tmp_path / "out" / "results.csv")
    gpcc = [r for r in rows if r.codec == "gpcc"]
    assert len(gpcc) == 16 and {r.setting.split(",")[0] for r in gpcc} == {"mode=octree", "mode=trisoup"}
    finest = min(gpcc, key=lambda r: r.d_e)
    assert finest.d_e < 0.1 and finest.iou > 0.3 and finest.n_decoded > 1000
    assert all(r.n_decoded > 0 and 0 <= r.iou <= 1 and r.d_perp <= r.d_e for r in gpcc)
