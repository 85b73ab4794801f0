"""Training runs a new user starts: no validation submaps, a time budget, the files written; two DDP processes."""

import csv
import dataclasses
import json
import stat
import subprocess
import sys

import numpy as np
import pytest
import torch

from mapsqueeze.data.mapping import Submap, write_dataset
from mapsqueeze.io import write_points
from mapsqueeze.model import load_network
from mapsqueeze.train import TrainConfig, one_cycle, retime_one_cycle, steps_within, weights_digest


@pytest.fixture
def train_only_dataset(tmp_path):
    rng = np.random.default_rng(0)
    submaps = []
    for index in range(2):
        points = np.column_stack([rng.uniform(0, 40, 1500), rng.uniform(0, 40, 1500), rng.normal(1, 0.05, 1500)])
        submaps.append(Submap(points, np.array([20.0, 20.0, 1.0]), np.array([[0, 0, 0], [40, 40, 15.0]]), "flat",
                              index, None, "train"))
    write_dataset(tmp_path / "data", submaps, {})
    return tmp_path / "data"


@pytest.mark.slow
def test_training_without_validation_names_the_training_chamfer(run_cli, train_only_dataset, tmp_path):
    out = tmp_path / "run"
    code, printed, err = run_cli("train", str(train_only_dataset), "-o", str(out), "--rate", "e3", "--epochs", "2",
                                 "--batch-size", "1", "--max-steps", "2")
    assert code == 0, err
    assert "best validation" not in printed and "no validation submaps" in printed
    assert "lowest training Chamfer" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["best_val_chamfer_m2"] is None and summary["best_train_chamfer_m2"] > 0
    config = json.loads((out / "best" / "config.json").read_text())
    assert "val_chamfer_m2" not in config["extra"] and config["extra"]["train_chamfer_m2"] > 0
    for name in ("model.safetensors", "config.json"):  # 0o666 minus the umask (0o022 here), as `open` makes
        assert stat.S_IMODE((out / "best" / name).stat().st_mode) == 0o644


def test_one_cycle_is_retimed_to_the_steps_that_fit():
    cfg = TrainConfig()
    parameter = torch.zeros(1, requires_grad=True)
    optimiser = torch.optim.SGD([parameter], lr=cfg.max_lr)
    scheduler = one_cycle(optimiser, 1000, cfg)  # 200 epochs' worth: 6 steps would stay in warm-up
    rates = []
    for step in range(1, 21):
        optimiser.step()
        scheduler.step()
        rates.append(scheduler.get_last_lr()[0])
        if step == 3:
            retime_one_cycle(scheduler, steps_within(1.0, elapsed_s=9.0, steps_taken=3, step_s=3.0), cfg)
    assert steps_within(1.0, 9.0, 3, 3.0) == 20
    assert max(rates) > 0.9 * cfg.max_lr  # near the peak within the budget (unretimed: 2e-6 after 20 steps)
    assert rates[-1] < 1.1 * cfg.end_lr  # and the cycle ends at its final rate


def _tiny_dataset(folder):
    """Four 12 x 12 m clouds of 1,500 points (a ground and a wall): a plain folder, every file in every split."""
    folder.mkdir()
    for seed in range(4):
        rng = np.random.default_rng(seed)
        ground = np.column_stack([rng.uniform(0, 12, 1000), rng.uniform(0, 12, 1000), rng.normal(0.3, 0.02, 1000)])
        wall = np.column_stack([rng.uniform(0, 12, 500), rng.normal(6.0, 0.02, 500), rng.uniform(0.3, 3.0, 500)])
        write_points(folder / f"cloud{seed}.ply", np.concatenate([ground, wall]))
    return folder


def _train_two_processes(dataset, out, *options):
    command = [sys.executable, "-m", "mapsqueeze", "train", str(dataset), "-o", str(out), "--rate", "e1",
               "--epochs", "2", "--batch-size", "1", "--val-limit", "1", "--nproc", "2", *options]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    with open(out / "log.csv") as log:
        rows = list(csv.DictReader(log))
    return json.loads((out / "summary.json").read_text()), rows


@pytest.mark.slow
def test_two_gloo_processes_hold_identical_weights_write_once_and_resume(tmp_path):
    dataset, out = _tiny_dataset(tmp_path / "data"), tmp_path / "run"
    summary, rows = _train_two_processes(dataset, out, "--max-steps", "2")  # stops after the first of two epochs
    saved = weights_digest(load_network(out / "last")[0])
    assert summary["processes"] == 2 and summary["steps"] == 2  # 4 clouds / (2 processes x batch 1)
    assert summary["process_weights_sha256"] == [saved, saved]
    assert [row["epoch"] for row in rows] == ["1"]  # one process logs
    assert sorted(p.name for p in out.iterdir()) == ["best", "last", "log.csv", "summary.json"]

    summary, rows = _train_two_processes(dataset, out, "--max-steps", "4")  # resumes with the second epoch
    resumed = weights_digest(load_network(out / "last")[0])
    assert summary["steps"] == 4 and [row["epoch"] for row in rows] == ["1", "2"]
    assert summary["process_weights_sha256"] == [resumed, resumed] and resumed != saved


@pytest.mark.slow
def test_a_cycle_fitted_to_fewer_steps_than_the_time_holds_ends_the_run(run_cli, train_only_dataset, tmp_path,
                                                                        monkeypatch):
    """With --max-minutes the cycle is fitted to the speed of the first steps; when later steps run faster the
    cycle ends before the time does, and the run stops there (it used to step the finished schedule: ValueError)."""
    import mapsqueeze.train as train

    monkeypatch.setattr(train, "steps_within", lambda minutes, elapsed_s, steps_taken, step_s: steps_taken + 2)
    out = tmp_path / "run"
    code, printed, err = run_cli("train", str(train_only_dataset), "-o", str(out), "--rate", "e3", "--epochs", "4",
                                 "--batch-size", "1", "--max-minutes", "30")
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == train.STEPS_BEFORE_RETIMING + 2


@pytest.mark.slow
def test_encoder_only_training_on_the_mean_distance_keeps_the_decoder_and_reads_the_init_models_files(
        run_cli, train_only_dataset, tmp_path):
    """`train --encoder-only --objective mean-distance` from the shipped e1: only encoder weights change (the decoder
    and the batch-norm statistics stay the init's), the log and summary name the mean distance, and the model
    records the init's digest, so a file the shipped e1 wrote decodes with it to the same points."""
    import mapsqueeze
    from mapsqueeze.model.config import SAME_DECODER_KEY
    from mapsqueeze.model.shipped import SHIPPED_DIR

    out = tmp_path / "run"
    code, printed, err = run_cli("train", str(train_only_dataset), "-o", str(out), "--rate", "e1", "--epochs", "1",
                                 "--batch-size", "1", "--max-steps", "2", "--init", str(SHIPPED_DIR / "e1"),
                                 "--encoder-only", "--objective", "mean-distance")
    assert code == 0, err
    assert "lowest training mean distance" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["best_train_mean_distance_m"] > 0 and "best_train_chamfer_m2" not in summary
    with open(out / "log.csv") as log:
        assert next(csv.reader(log))[4:6] == ["train_mean_distance_m", "val_mean_distance_m"]
    init, init_sha = load_network(SHIPPED_DIR / "e1")
    trained, _ = load_network(out / "last")
    before, after = init.state_dict(), trained.state_dict()
    changed = {name for name in before if not torch.equal(before[name], after[name])}
    assert changed and all(name.startswith("encoder.") for name in changed)
    assert not any(name.endswith(("running_mean", "running_var")) for name in changed)
    extra = trained.config.extra
    assert extra["objective"] == "mean-distance" and extra["encoder_only"] is True
    assert extra[SAME_DECODER_KEY] == [init_sha, *init.config.extra.get(SAME_DECODER_KEY, [])]
    points = np.random.default_rng(3).random((4000, 3)) * [30, 30, 3]
    data = mapsqueeze.compress(points, model="e1", workers=1)
    assert np.array_equal(mapsqueeze.decompress(data, model=str(out / "last"), workers=1),
                          mapsqueeze.decompress(data, workers=1))


def test_encoder_only_needs_an_init_model_of_its_architecture_and_an_unknown_objective_is_refused(
        run_cli, train_only_dataset, tmp_path):
    from mapsqueeze.model.shipped import SHIPPED_DIR

    code, _, err = run_cli("train", str(train_only_dataset), "-o", str(tmp_path / "a"), "--encoder-only")
    assert code != 0 and "--encoder-only trains the encoder of a model given by --init" in err
    code, _, err = run_cli("train", str(train_only_dataset), "-o", str(tmp_path / "b"), "--objective", "l2")
    assert code != 0 and "unknown objective 'l2'; choose one of chamfer, mean-distance" in err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    code, _, err = run_cli("train", str(train_only_dataset), "-o", str(tmp_path / "c"), "--rate", "e2",
                           "--init", str(SHIPPED_DIR / "e1"), "--encoder-only", "--max-steps", "1")
    assert code != 0 and "the decoder of" in err and "differs from the e2 architecture's" in err


@pytest.mark.parametrize("changed", [{"map_size": 16.0}, {"decoder_kernel_radius": 0.1}])
def test_encoder_only_refuses_an_init_model_whose_config_decodes_its_weights_otherwise(train_only_dataset, tmp_path,
                                                                                      changed):
    """The decoder's weights alone do not fix what a file decodes to: an init model whose config scales or offsets
    the same weights otherwise is refused before training, so no model lists the digest of files it would decode
    to other points."""
    import dataclasses

    from mapsqueeze.errors import MapsqueezeError
    from mapsqueeze.model import ModelConfig, build_model, save_model
    from mapsqueeze.train import train

    config = ModelConfig.for_rate("e1", tile_size=(8.0, 8.0, 4.0), map_size=8.0, max_input_points=2000)
    init = save_model(build_model(config, seed=1), tmp_path / "init")
    cfg = TrainConfig(epochs=1, batch_size=1, max_steps=1, encoder_only=True)
    (setting,) = changed
    with pytest.raises(MapsqueezeError, match=f"differs from the e1 architecture's \\(settings {setting}\\)"):
        train(train_only_dataset, tmp_path / "run", dataclasses.replace(config, **changed), cfg, init=init)


def test_a_run_resumes_only_with_its_objective_and_encoder_only_setting(train_only_dataset, tmp_path):
    """`best` and the log compare figures of one objective, and the optimiser state holds the parameters of one
    setting: a resume with another --objective or --encoder-only is one error line, not a mixed run or a
    traceback from the optimiser's state."""
    from mapsqueeze.errors import MapsqueezeError
    from mapsqueeze.model import ModelConfig, build_model, save_model
    from mapsqueeze.train import train

    config = ModelConfig.for_rate("e1", tile_size=(8.0, 8.0, 4.0), map_size=8.0, max_input_points=2000)
    init = save_model(build_model(config, seed=1), tmp_path / "init")
    out = tmp_path / "run"
    cfg = TrainConfig(epochs=1, batch_size=1, max_steps=1, encoder_only=True, objective="mean-distance")
    train(train_only_dataset, out, config, cfg, init=init)
    for other in ({"objective": "chamfer"}, {"encoder_only": False}):
        with pytest.raises(MapsqueezeError, match="holds a run of objective mean-distance, encoder only: resume it"):
            train(train_only_dataset, out, config, dataclasses.replace(cfg, **other), init=init)
    assert train(train_only_dataset, out, config, cfg)["steps"] == 1  # the same settings resume (nothing left)
