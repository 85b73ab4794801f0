"""Model commands: import-depoco, fit-density, train, models."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from mapsqueeze.cli.app import app, make_console, print_table

console = make_console()


@app.command("import-depoco")
def import_depoco(
    ref_dir: Path = typer.Argument(..., help="Reference folder with eX.yaml, enc_best.pth, dec_best.pth"),
    out: Path = typer.Option(..., "-o", "--out", help="Output model folder (config.json + model.safetensors)"),
):
    """Convert a released reference (DEPOCO) checkpoint into mapsqueeze's safetensors + JSON format."""
    from mapsqueeze.model import import_reference, save_model

    network = import_reference(ref_dir)
    save_model(network, out)
    c = network.config
    console.print(f"imported {c.name}: r_s = {c.subsampling_dist} m, upsampling {list(c.upsampling_factors)} "
                  f"-> {out}")


@app.command("fit-density")
def fit_density(
    dataset: Path = typer.Argument(..., help="Dataset folder (manifest.json) or folder of point-cloud files"),
    split: str = typer.Option("train", help="Split to fit on (ignored for plain folders)"),
):
    """Fit A(r_s) = a * r_s^-b (embedding points per map point) by least squares and print a, b, residual."""
    from mapsqueeze.model.density import fit_density_law
    from mapsqueeze.train import load_samples

    samples = load_samples(dataset, (split,))
    fit = fit_density_law([s.points.astype("float64") for s in samples])
    table = Table(title=f"A(r) = a * r^-b on {len(samples)} clouds")
    table.add_column("r_s (m)")
    table.add_column("mean rate")
    table.add_column("fitted")
    for r, rate in zip(fit.grids_m, fit.mean_rates):
        table.add_row(f"{r:g}", f"{rate:.5f}", f"{fit.a * r ** -fit.b:.5f}")
    print_table(table)
    console.print(f"a = {fit.a:.5f}  b = {fit.b:.4f}  rmse = {fit.rmse:.2e}")


@app.command("train")
def train_cmd(
    dataset: Path = typer.Argument(..., help="Dataset folder written by build-map or simulate"),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder (best/, last/, log.csv)"),
    rate: str = typer.Option("e1", help="Rate point e0|e1|e2|e3 (r_s = 3.0/2.0/1.2/1.0 m)"),
    epochs: int = typer.Option(200, min=1),
    batch_size: int = typer.Option(3, min=1),
    max_lr: float = typer.Option(1e-4, min=0.0),
    beta: float = typer.Option(0.2, min=0.0, help="Weight of the intermediate Chamfer terms (0 = ablation)"),
    max_steps: Optional[int] = typer.Option(None, min=1, help="Stop after this many optimiser steps"),
    max_minutes: Optional[float] = typer.Option(None, min=0.0, help="Stop after this many minutes (the one-cycle "
                                                "schedule is fitted to the steps that fit in them)"),
    init: Optional[Path] = typer.Option(None, help="Initialise matching weights from another model folder"),
    density_a: Optional[float] = typer.Option(None, help="Density law a (default: the paper's 0.006)"),
    density_b: Optional[float] = typer.Option(None, help="Density law b (default: the paper's 1.764)"),
    val_limit: Optional[int] = typer.Option(None, min=1, help="Validate on at most this many submaps"),
    objective: str = typer.Option("chamfer", help="chamfer (the paper's loss) or mean-distance (encode-time "
                                  "refinement's: D_e against every point, with the model's dead zone)"),
    encoder_only: bool = typer.Option(False, "--encoder-only", help="Train only the encoder of the --init model, "
                                      "its decoder frozen (files decode with the same decoder)"),
    seed: int = typer.Option(0),
    device: str = typer.Option("cpu", help="cpu or cuda"),
    no_resume: bool = typer.Option(False, "--no-resume", help="Start over even if out/last exists"),
    nproc: int = typer.Option(1, "--nproc", min=1, help="Train in N processes (DistributedDataParallel: gloo on "
                              "CPU, nccl with --device cuda, one GPU each); each step averages N x batch-size "
                              "submaps. Same as torchrun --nproc-per-node N -m mapsqueeze train ..."),
):
    """Train the autoencoder of one rate point (Adam, one-cycle cosine lr, batch by gradient accumulation)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from mapsqueeze.model import ModelConfig
    from mapsqueeze.train import OBJECTIVES, TrainConfig, train, train_processes

    overrides = {k: v for k, v in (("density_a", density_a), ("density_b", density_b)) if v is not None}
    model_config = ModelConfig.for_rate(rate, **overrides)
    cfg = TrainConfig(epochs=epochs, batch_size=batch_size, max_lr=max_lr, beta=beta, max_steps=max_steps,
                      max_minutes=max_minutes, val_limit=val_limit, seed=seed, objective=objective,
                      encoder_only=encoder_only)
    if nproc > 1:  # progress: out/log.csv, one row per epoch
        summary = train_processes(nproc, dataset, out, model_config, cfg, device=device, resume=not no_resume,
                                  init=init)
    else:
        with Progress(TextColumn("epoch {task.fields[epoch]} step {task.completed}"), BarColumn(),
                      TextColumn("loss {task.fields[loss]:.5f}"), TimeElapsedColumn(), console=console,
                      disable=os.environ.get("RANK", "0") != "0" or not console.is_terminal) as bar:
            # under torchrun process 0 reports; piped, no bar (the summary line below)
            task = bar.add_task("train", total=max_steps, epoch=0, loss=float("nan"))
            summary = train(dataset, out, model_config, cfg, device=device, resume=not no_resume, init=init,
                            progress=lambda e, s, l: bar.update(task, completed=s, epoch=e + 1, loss=l))
    if os.environ.get("RANK", "0") != "0":
        return
    metric = OBJECTIVES[cfg.objective]
    name, unit = ("Chamfer", "m^2") if cfg.objective == "chamfer" else ("mean distance", "m")
    if summary[f"best_val_{metric}"] is None:
        best = (f"no validation submaps: best/ holds the lowest training {name}, "
                f"{summary[f'best_train_{metric}']:.5f} {unit},")
    else:
        best = f"best validation {name} {summary[f'best_val_{metric}']:.5f} {unit}"
    console.print(f"{best} after {summary['steps']} steps ({summary['minutes']:.1f} min, {summary['processes']} "
                  f"process(es)) -> {out / 'best'}")


@app.command("models")
def models_cmd():
    """List the models shipped with the package."""
    from mapsqueeze.model import load_network, shipped_models
    from mapsqueeze.model.shipped import SHIPPED_DIR

    table = Table(title="shipped models")
    for col in ("name", "r_s (m)", "upsampling", "validation", "last training run (history: model card)"):
        table.add_column(col)
    for name in shipped_models():
        network, _ = load_network(SHIPPED_DIR / name)
        c = network.config
        if "val_mean_distance_m" in c.extra:
            validation = f"mean distance {c.extra['val_mean_distance_m']:.4f} m"
        else:
            validation = f"Chamfer {c.extra.get('val_chamfer_m2', float('nan')):.4f} m^2"
        run = f"{c.extra.get('steps', '?')} steps on {Path(str(c.extra.get('dataset', '?'))).name}"
        if c.extra.get("encoder_only"):
            run += " (encoder only)"
        table.add_row(name, f"{c.subsampling_dist:g}", "x".join(map(str, c.upsampling_factors)), validation, run)
    print_table(table)
