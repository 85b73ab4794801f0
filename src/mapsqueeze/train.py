"""Training loop of the autoencoder (paper Sec. IV-A): Adam + one-cycle cosine schedule, batch by gradient
accumulation, validation each epoch with the best checkpoint kept, resumable, CSV log, rich progress. Beyond the
paper: the encoder alone on encode-time refinement's objective (`OBJECTIVES`, `TrainConfig.encoder_only`).

Distributed data parallel: run under `torchrun --nproc-per-node N -m mapsqueeze train ...` (or `train --nproc N`,
`train_processes`): every process trains on its share of each epoch's submaps (gloo on CPU, nccl on GPUs), the
gradients are averaged, and process 0 alone validates and writes the checkpoints, the log and the summary.
"""

from __future__ import annotations

import csv
import gc
import hashlib
import json
import math
import os
import socket
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from mapsqueeze.errors import MapsqueezeError, ModelError
from mapsqueeze.geometry.threads import set_threads
from mapsqueeze.model import Autoencoder, ModelConfig, build_model, load_network, save_model
from mapsqueeze.model.config import DECODING_SETTINGS, SAME_DECODER_KEY
from mapsqueeze.model.devices import torch_device
from mapsqueeze.model.loss import chamfer_loss, depoco_loss, mean_distance_loss

OBJECTIVES = {"chamfer": "chamfer_m2", "mean-distance": "mean_distance_m"}
"""Training objectives and the name of the figure each reports (log columns, summary, the model's config):
- chamfer: the paper's loss (eq. 8), the Chamfer distance of the output and the intermediate clouds to the input
  (at most max_points of the cloud), in m^2;
- mean-distance: encode-time refinement's objective (`refine.refine_embedding`): the mean nearest-neighbour distance
  both ways between the decoder's output and every point of the cloud, with the model's dead zone
  (`ModelConfig.refine_dead_zone_m`), in m. Trained with --encoder-only, the encoder learns to give the embedding that
  refinement would move it towards, under the decoder every file of that model decodes with."""


@dataclass
class TrainConfig:
    """Optimisation settings; defaults are the paper's (lr 1e-6 -> 1e-4 over 10 % -> 1e-5, cosine, batch 3)."""

    epochs: int = 200
    batch_size: int = 3
    start_lr: float = 1e-6
    max_lr: float = 1e-4
    end_lr: float = 1e-5
    pct_start: float = 0.1
    beta: float = 0.2  # weight of the intermediate-cloud Chamfer terms (eq. 8); 0 = ablation without it
    max_points: int = 30000
    seed: int = 0
    augment: bool = True  # random 90-degree z rotations, flips and sub-grid shifts
    max_steps: int | None = None  # stop after this many optimiser steps (time-boxed runs)
    max_minutes: float | None = None  # stop (after checkpointing) when this wall time is exceeded
    val_limit: int | None = None  # validate on at most this many submaps
    objective: str = "chamfer"  # a key of OBJECTIVES
    encoder_only: bool = False  # train the encoder alone: the decoder (from init) frozen, batch norm in eval mode


@dataclass
class Sample:
    """One training cloud in metres, relative to its own minimum corner (float32)."""

    name: str
    points: np.ndarray


def load_samples(dataset: Path, splits: tuple[str, ...]) -> list[Sample]:
    """Submaps of a dataset directory (manifest.json written by `build-map`/`simulate`/`tile`) in the given
    splits, or every point-cloud file of a plain folder (all splits)."""
    from mapsqueeze.data.mapping import MANIFEST_NAME, read_dataset
    from mapsqueeze.io import point_cloud_files, read_points

    dataset = Path(dataset)
    if (dataset / MANIFEST_NAME).is_file():
        clouds = [(r.path.stem, r.local_points()) for r in read_dataset(dataset).records if r.split in splits]
    elif dataset.is_dir():
        clouds = [(p.stem, read_points(p)) for p in point_cloud_files(dataset)]
    else:
        raise MapsqueezeError(f"dataset {dataset} not found")
    return [Sample(name, (pts - pts.min(axis=0)).astype(np.float32)) for name, pts in clouds if len(pts)]


def augment_points(points: np.ndarray, rng: np.random.Generator, extent: float) -> np.ndarray:
    """Random multiple-of-90-degree rotation about z, random x flip and a shift that keeps the cloud in [0, extent)."""
    pts = points.astype(np.float64)
    center = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    pts = pts - center
    k = rng.integers(4)
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]
    pts = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64).T
    if rng.random() < 0.5:
        pts[:, 0] = -pts[:, 0]
    pts -= pts.min(axis=0)
    slack = np.maximum(extent - 1e-3 - pts.max(axis=0), 0.0)
    pts += rng.random(3) * np.minimum(slack, 2.0)
    return pts.astype(np.float32)


def select_points(points: np.ndarray, max_points: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= max_points:
        return points
    return points[rng.choice(len(points), max_points, replace=False)]


STEPS_BEFORE_RETIMING = 3
"""With max_minutes, the one-cycle schedule is fitted to the time budget after this many optimiser steps."""


def one_cycle(optimizer, total_steps: int, cfg: TrainConfig):
    return torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=cfg.max_lr, total_steps=max(total_steps, 2), pct_start=cfg.pct_start,
        anneal_strategy="cos", div_factor=cfg.max_lr / cfg.start_lr, final_div_factor=cfg.start_lr / cfg.end_lr,
        cycle_momentum=False)


def retime_one_cycle(scheduler, total_steps: int, cfg: TrainConfig) -> None:
    """Stretch or shrink a one-cycle schedule (warm-up, then cosine decay) to `total_steps` in all, keeping the
    steps already taken; the learning rate of the next step follows the new schedule."""
    state = scheduler.state_dict()
    total_steps = max(total_steps, scheduler.last_epoch + 2)
    state["total_steps"] = total_steps
    state["_schedule_phases"][0]["end_step"] = float(cfg.pct_start * total_steps) - 1
    state["_schedule_phases"][-1]["end_step"] = total_steps - 1
    scheduler.load_state_dict(state)


def steps_within(minutes: float, elapsed_s: float, steps_taken: int, step_s: float) -> int:
    """Optimiser steps a run reaches in `minutes` of wall time: the steps taken so far plus as many more of
    `step_s` seconds as the remaining time holds."""
    return steps_taken + max(0, int((60 * minutes - elapsed_s) / max(step_s, 1e-9)))


@torch.no_grad()
def validate(network: Autoencoder, samples: list[Sample], device: torch.device, objective: str = "chamfer") -> float:
    """The objective's figure (`OBJECTIVES`) on the validation clouds, averaged: the Chamfer distance (m^2) between
    each cloud's encoder input (<= max_input_points) and its reconstruction, or the mean distance (m) between the
    reconstruction and every point of the cloud. Leaves the network in the mode it found."""
    training = network.training
    network.eval()
    scale = network.config.map_size
    rng = np.random.default_rng(12345)
    values = []
    for s in samples:
        pts = torch.from_numpy(select_points(s.points, network.config.max_input_points, rng) / scale).to(device)
        out, _, _ = network(pts)
        if objective == "chamfer":
            values.append(chamfer_loss(pts, out).item() * scale**2)
        else:
            cloud = torch.from_numpy(s.points / scale).to(device)
            values.append(mean_distance_loss(cloud, out, dead_zone=_dead_zone(network.config)).item() * scale)
    network.train(training)
    return float(np.mean(values)) if values else math.nan


def _dead_zone(config: ModelConfig) -> float:
    """The mean-distance objective's dead zone for this model (refinement's, `ModelConfig.refine_dead_zone_m`),
    normalised units."""
    return config.refine_dead_zone_m / config.map_size


def trained_parameters(network: Autoencoder, cfg: TrainConfig) -> list[torch.nn.Parameter]:
    """The parameters the optimiser steps: all of them, or with cfg.encoder_only the encoder's, the decoder's
    frozen (requires_grad off)."""
    if not cfg.encoder_only:
        return list(network.parameters())
    network.decoder.requires_grad_(False)
    return list(network.encoder.parameters())


def init_from(network: Autoencoder, source_dir: Path) -> int:
    """Copy every learned tensor whose name and shape match from another model (e.g. another rate point); never
    the kernel point positions, geometry derived from this model's own configuration."""
    other, _ = load_network(source_dir)
    own = network.state_dict()
    matched = {k: v for k, v in other.state_dict().items()
               if k in own and own[k].shape == v.shape and not k.endswith("kernel_points")}
    own.update(matched)
    network.load_state_dict(own)
    return len(matched)


def same_decoder_digests(network: Autoencoder, model_dir: Path) -> list[str]:
    """The weights digests whose files `network` decodes when it holds the decoder of `model_dir`: that model's own
    and those it records (`SAME_DECODER_KEY`). MapsqueezeError when the decoders or their DECODING_SETTINGS differ."""
    other, sha = load_network(model_dir)
    own, theirs = network.decoder.state_dict(), other.decoder.state_dict()
    differing = [name for name in DECODING_SETTINGS if getattr(network.config, name) != getattr(other.config, name)]
    if differing or own.keys() != theirs.keys() or not all(
            own[k].shape == theirs[k].shape and torch.equal(own[k].cpu(), theirs[k]) for k in own):
        settings = f" (settings {', '.join(differing)})" if differing else ""
        raise MapsqueezeError(f"--encoder-only: the decoder of {model_dir} differs from the {network.config.name} "
                              f"architecture's{settings}; pass a model of this rate point with --init")
    return [sha, *other.config.extra.get(SAME_DECODER_KEY, [])]


def weights_digest(network: torch.nn.Module) -> str:
    """SHA-256 of every parameter and buffer (state_dict order): equal digests, identical weights."""
    digest = hashlib.sha256()
    for name, tensor in network.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


@dataclass(frozen=True)
class _Process:
    """This process's place in a distributed run (rank 0 of 1 when not distributed)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def writer(self) -> bool:
        return self.rank == 0


def _join_process_group(device: str) -> tuple[_Process, torch.device]:
    """Join the process group torchrun (or train_processes) describes in RANK / WORLD_SIZE / LOCAL_RANK, if any: nccl
    bound to one GPU per process for cuda, gloo otherwise. This process's place and device (`torch_device`'s checks)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    dev = torch_device(device, int(os.environ.get("LOCAL_WORLD_SIZE", world)))
    if world <= 1:
        return _Process(), dev
    import torch.distributed as dist

    process = _Process(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", "0")))
    if dev.type == "cuda":
        dev = torch.device("cuda", process.local_rank)
        torch.cuda.set_device(dev)
    if not dist.is_initialized():
        backend, bound = ("nccl", dev) if dev.type == "cuda" else ("gloo", None)
        dist.init_process_group(backend, device_id=bound)
    return process, dev


def _all_ranks(process: _Process, flag: bool, device: torch.device) -> bool:
    """True on every process when it is true on any (a stop decision all processes take together)."""
    if process.world == 1:
        return flag
    import torch.distributed as dist

    value = torch.tensor([int(flag)], device=device)
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item())


def _smallest(process: _Process, value: int, device: torch.device) -> int:
    """The smallest of every process's value (a step budget all processes agree on)."""
    if process.world == 1:
        return value
    import torch.distributed as dist

    tensor = torch.tensor([int(value)], device=device)
    dist.all_reduce(tensor, op=dist.ReduceOp.MIN)
    return int(tensor.item())


def _average_buffers(process: _Process, network: torch.nn.Module) -> None:
    """Average the floating-point buffers (batch-norm running statistics, which each process updates from its own
    submaps) over the processes, so that all of them hold, and process 0 saves, the same model."""
    if process.world == 1:
        return
    import torch.distributed as dist

    for buffer in network.buffers():
        if buffer.is_floating_point():
            dist.all_reduce(buffer.data, op=dist.ReduceOp.SUM)
            buffer.data /= process.world


def _rank_digests(process: _Process, network: torch.nn.Module) -> list[str]:
    """Every process's weights_digest, gathered on all of them."""
    digest = weights_digest(network)
    if process.world == 1:
        return [digest]
    import torch.distributed as dist

    digests: list = [None] * process.world
    dist.all_gather_object(digests, digest)
    return digests


def train(dataset: Path, out_dir: Path, model_config: ModelConfig, cfg: TrainConfig, device: str = "cpu",
          resume: bool = True, init: Path | None = None, progress=None) -> dict:
    """Train and keep `out_dir/best` (lowest validation figure of cfg.objective, `OBJECTIVES`; lowest training
    figure when the dataset has no validation submaps) and `out_dir/last` (+ optimiser state) up to date. With
    cfg.encoder_only only the encoder of the `init` model trains, and the model records the digests whose files
    its decoder reads (`SAME_DECODER_KEY`). The one-cycle schedule spans
    cfg.epochs, or cfg.max_steps, or (cfg.max_minutes) the steps that fit in the time budget at the speed of the
    first STEPS_BEFORE_RETIMING steps, whichever is fewest.

    Returns a summary dict (also written to out_dir/summary.json). Under torchrun (WORLD_SIZE > 1) each of the N
    processes takes every N-th submap of an epoch's order and makes cfg.batch_size passes per step, so a step
    averages the gradients of N x batch_size submaps; process 0 alone validates and writes; the summary lists
    every process's weights digest (`weights_digest`, identical by construction and checked).
    """
    if cfg.objective not in OBJECTIVES:
        raise MapsqueezeError(f"unknown objective {cfg.objective!r}; choose one of {', '.join(OBJECTIVES)}")
    if cfg.encoder_only and init is None and not (resume and (Path(out_dir) / "last" / "train_state.pt").is_file()):
        raise MapsqueezeError("--encoder-only trains the encoder of a model given by --init (its decoder kept)")
    process, dev = _join_process_group(device)
    if process.world == 1:
        return _train(dataset, Path(out_dir), model_config, cfg, dev, resume, init, progress, process)
    import torch.distributed as dist

    try:
        summary = _train(dataset, Path(out_dir), model_config, cfg, dev, resume, init, progress, process)
        gc.collect()  # the DDP wrapper's reducer holds the process group: free it before the group goes
        dist.barrier()  # a process that tears down its gloo pairs while another still uses them aborts (SIGABRT)
        return summary
    finally:
        dist.destroy_process_group()


def _train(dataset: Path, out_dir: Path, model_config: ModelConfig, cfg: TrainConfig, dev: torch.device,
           resume: bool, init: Path | None, progress, process: _Process) -> dict:
    if process.writer:
        out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    train_set = load_samples(dataset, ("train",))
    val_set = load_samples(dataset, ("val",))[: cfg.val_limit]
    if not train_set:
        raise MapsqueezeError(f"{dataset}: no training submaps")
    network = build_model(model_config, seed=cfg.seed).to(dev)
    if init is not None:
        init_from(network, init)
        if cfg.encoder_only:  # files of the init model decode with this one
            network.config.extra = {**network.config.extra, SAME_DECODER_KEY: same_decoder_digests(network, init)}
    optimizer = torch.optim.Adam(trained_parameters(network, cfg), lr=cfg.max_lr)
    steps_per_epoch = max(1, len(train_set) // (cfg.batch_size * process.world))
    scheduler = one_cycle(optimizer, cfg.epochs * steps_per_epoch, cfg)
    state_path = out_dir / "last" / "train_state.pt"
    start_epoch, step, best = 0, 0, math.inf
    if resume and state_path.is_file():
        state = torch.load(state_path, map_location="cpu", weights_only=True)  # the optimiser moves its own state
        run = (state.get("objective", "chamfer"), bool(state.get("encoder_only", False)))  # older states: the paper's
        if run != (cfg.objective, cfg.encoder_only):
            raise MapsqueezeError(f"{out_dir} holds a run of objective {run[0]}{', encoder only' * run[1]}: resume it "
                                  "with the same --objective and --encoder-only, or start over with --no-resume")
        network, _ = load_network(out_dir / "last")
        network.to(dev)
        optimizer = torch.optim.Adam(trained_parameters(network, cfg), lr=cfg.max_lr)
        scheduler = one_cycle(optimizer, cfg.epochs * steps_per_epoch, cfg)
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        start_epoch, step, best = int(state["epoch"]), int(state["step"]), float(state["best"])
    model = network
    if process.world > 1:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(network, device_ids=[dev.index] if dev.type == "cuda" else None)
    metric = OBJECTIVES[cfg.objective]
    log, writer = _open_log(out_dir / "log.csv", metric) if process.writer else (None, None)
    scale = model_config.map_size
    dead_zone = _dead_zone(model_config)
    t0 = time.time()
    first_step, planned_steps = step, cfg.epochs * steps_per_epoch
    if cfg.max_steps:
        planned_steps = min(planned_steps, cfg.max_steps)
        retime_one_cycle(scheduler, planned_steps, cfg)
    stop = False
    # With cfg.encoder_only eval mode throughout: the encoder's batch norms keep the running statistics the decoder
    # was trained with, so training computes what compression does.
    network.train(not cfg.encoder_only)
    for epoch in range(start_epoch, cfg.epochs):
        rng = np.random.default_rng([cfg.seed, epoch])
        order = rng.permutation(len(train_set))[: steps_per_epoch * cfg.batch_size * process.world]
        if process.world > 1:  # this process's share, with its own augmentation draws
            order, rng = order[process.rank::process.world], np.random.default_rng([cfg.seed, epoch, process.rank])
        losses, figures = [], []
        optimizer.zero_grad()
        for i, idx in enumerate(order):
            pts = train_set[idx].points
            if cfg.augment:
                pts = augment_points(pts, rng, scale)
            inputs = torch.from_numpy(select_points(pts, cfg.max_points, rng) / scale).to(dev)
            last_pass = i % cfg.batch_size == cfg.batch_size - 1
            with _gradient_sync(model, last_pass):  # DDP averages the gradients once per step
                output, intermediate, _ = model(inputs)
                if cfg.objective == "chamfer":
                    loss, main = depoco_loss(inputs, output, intermediate, cfg.beta)
                else:  # against every point of the cloud, as refinement
                    loss = main = mean_distance_loss(torch.from_numpy(pts / scale).to(dev), output,
                                                     dead_zone=dead_zone)
                (loss / cfg.batch_size).backward()
            losses.append(loss.item())
            figures.append(main.item() * (scale**2 if cfg.objective == "chamfer" else scale))
            if last_pass:
                optimizer.step()
                optimizer.zero_grad()
                scheduler.step()
                step += 1
                if cfg.max_minutes and step - first_step == STEPS_BEFORE_RETIMING:  # fit the cycle to the time
                    elapsed = time.time() - t0
                    budget = steps_within(cfg.max_minutes, elapsed, step, elapsed / STEPS_BEFORE_RETIMING)
                    retime_one_cycle(scheduler, _smallest(process, min(planned_steps, budget), dev), cfg)
                if progress is not None and process.writer:
                    progress(epoch, step, float(np.mean(losses[-cfg.batch_size:])))
                if _all_ranks(process, bool((cfg.max_steps and step >= cfg.max_steps) or (
                        cfg.max_minutes and time.time() - t0 > 60 * cfg.max_minutes)
                        or step >= scheduler.total_steps), dev):  # a retimed cycle can end before the time
                    stop = True
                    break
        _average_buffers(process, network)
        digests = _rank_digests(process, network)
        if len(set(digests)) != 1:
            raise ModelError(f"the training processes' weights differ after epoch {epoch + 1}: {digests}")
        if process.writer:
            # Without validation submaps the training figure picks best/, and is named as such everywhere.
            val = validate(network, val_set, dev, cfg.objective) if val_set else float(np.mean(figures))
            writer.writerow([epoch + 1, step, f"{scheduler.get_last_lr()[0]:.3e}", f"{np.mean(losses):.6f}",
                             f"{np.mean(figures):.6f}", f"{val:.6f}" if val_set else "", f"{time.time() - t0:.1f}"])
            log.flush()
            if val < best:
                best = val
                network.config.extra = {**network.config.extra, "epochs": epoch + 1, "steps": step,
                                        f"val_{metric}" if val_set else f"train_{metric}": val,
                                        "dataset": str(dataset), "beta": cfg.beta}
                if cfg.objective != "chamfer" or cfg.encoder_only:
                    network.config.extra.update(objective=cfg.objective, encoder_only=cfg.encoder_only)
                save_model(network, out_dir / "best")
            save_model(network, out_dir / "last")
            torch.save({"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "epoch": epoch + 1,
                        "step": step, "best": best, "objective": cfg.objective, "encoder_only": cfg.encoder_only},
                       state_path)  # a resume needs the same objective and encoder_only
        if stop:
            break
    summary = {f"best_val_{metric}": best if val_set else None, f"best_train_{metric}": None if val_set else best,
               "steps": step, "planned_steps": scheduler.total_steps, "minutes": (time.time() - t0) / 60,
               "train_config": asdict(cfg), "train_submaps": len(train_set), "val_submaps": len(val_set),
               "processes": process.world, "process_weights_sha256": _rank_digests(process, network)}
    if not process.writer:
        return summary
    log.close()
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if not (out_dir / "best" / "model.safetensors").is_file():
        raise ModelError("training produced no checkpoint")
    return summary


def _open_log(path: Path, metric: str):
    new_log = not path.is_file()
    log = open(path, "a", newline="")
    writer = csv.writer(log)
    if new_log:
        writer.writerow(["epoch", "step", "lr", "train_loss", f"train_{metric}", f"val_{metric}", "seconds"])
    return log, writer


def _gradient_sync(model: torch.nn.Module, sync: bool):
    """DDP's no_sync() on the passes that only accumulate gradients; nothing to do otherwise."""
    import contextlib

    if sync or not hasattr(model, "no_sync"):
        return contextlib.nullcontext()
    return model.no_sync()


def train_processes(nproc: int, dataset: Path, out_dir: Path, model_config: ModelConfig, cfg: TrainConfig,
                    device: str = "cpu", resume: bool = True, init: Path | None = None) -> dict:
    """`train` in nproc local processes (what `torchrun --nproc-per-node nproc` does), each with its share of
    the cores; returns the summary process 0 wrote. MapsqueezeError when a process fails."""
    import torch.multiprocessing as mp

    if nproc < 1:
        raise MapsqueezeError(f"--nproc must be at least 1, got {nproc}")
    torch_device(device, nproc)  # a device the processes cannot have fails here, once
    with socket.socket() as probe:  # a free port for the process group's rendezvous
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    try:
        mp.spawn(_train_process, args=(nproc, port, dataset, out_dir, model_config, cfg, device, resume, init),
                 nprocs=nproc, join=True)
    except mp.ProcessRaisedException as exc:
        last = str(exc).strip().splitlines()[-1]
        raise MapsqueezeError(f"a training process failed: {last}") from None
    except mp.ProcessExitedException as exc:
        raise MapsqueezeError(f"a training process died: {exc}") from None
    return json.loads((Path(out_dir) / "summary.json").read_text())


def _train_process(rank: int, nproc: int, port: int, *args) -> None:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    set_threads(max(1, cores // nproc))
    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(nproc), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    train(*args)
    # The process group is destroyed; leave without running C++ static destructors, which can still find a gloo
    # thread joinable at interpreter exit and abort ("terminate called without an active exception").
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
