"""Run every variant on every cloud and write the results: results.csv, run.json and the reports."""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from mapsqueeze.benchmark.clouds import collect_clouds
from mapsqueeze.benchmark.rows import Row, read_rows, write_rows
from mapsqueeze.benchmark.variants import Variant, build_variants
from mapsqueeze.errors import MapsqueezeError


DecodedCallback = Callable[[str, str, str, bytes, np.ndarray, np.ndarray, object], None]


def write_reports(rows: list[Row], out_dir: Path, final: bool = True) -> None:
    """Every report of the rows: results.md, and the plots (per-cloud plots only when final)."""
    from mapsqueeze.benchmark.plots import write_plots
    from mapsqueeze.benchmark.report import write_markdown

    write_markdown(rows, out_dir)
    write_plots(rows, out_dir, per_cloud=final)


def run_record(arguments: dict, variants: list[Variant]) -> dict:
    """What run.json holds: package version, arguments, the learned models' weight hashes, machine, start time."""
    from mapsqueeze.version import __version__

    weights = {f"{v.codec}:{v.setting.split(',')[0]}": v.weights for v in variants if v.weights}
    return {"version": __version__, "arguments": arguments, "model_weights_sha256": weights,
            "machine": {"python": platform.python_version(), "platform": platform.platform(),
                        "processor": platform.processor() or platform.machine()},
            "started": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def _write_json(record: dict, path: Path) -> None:
    from mapsqueeze.io import atomic_output

    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(record, indent=2) + "\n")


def reusable_rows(rows: list[Row], variants: list[Variant], log: Callable[[str], None]) -> list[Row]:
    """Earlier rows to keep: all rows of codecs and settings this run does not include, and rows of this run's
    variants made with the same model weights (the others are dropped, so they run again)."""
    weights = {v.key(): v.weights for v in variants}
    kept = [r for r in rows if weights.get((r.codec, r.setting), r.weights) == r.weights]
    if len(kept) < len(rows):
        log(f"{len(rows) - len(kept)} earlier results were made with other model weights; running them again")
    return kept


def run_benchmark(inputs: list[Path], codecs: list[str], out_dir: Path, models: list[str] | None = None,
                  precision: str = "q", split: str = "test", log: Callable[[str], None] = print,
                  progress: Callable[[str], None] | None = None, fresh: bool = False,
                  refine: tuple[int, ...] = (0,), every: int = 1, on_decoded: DecodedCallback | None = None,
                  device: str = "cpu") -> list[Row]:
    """Run every variant on every cloud; write results.csv, run.json, results.md, rd.png (+ rd_<cloud>.png).

    Results already in out_dir/results.csv are kept and their (cloud, codec, setting) not run again when made
    with the same model weights, so a long benchmark can be resumed or extended by more codecs later; fresh=True
    starts over. refine: the encode-time refinement steps the learned codecs run at (each a setting of its own).
    every=N runs on every N-th cloud only (the first, the (N+1)-th, ...; names unchanged, so a subset can be added
    to a full run's folder). on_decoded(cloud name, codec, setting, compressed bytes, original points, decoded points,
    metrics) is called after each result (the CLI writes viewer pages with it). device: where the learned codecs'
    networks run (`build_variants`; run.json records it, the rows kept from earlier runs may come from another).
    """
    from mapsqueeze.codec.compress import check_refine_steps
    from mapsqueeze.geometry.normals import normals_pca
    from mapsqueeze.metrics import evaluate

    if every < 1:
        raise MapsqueezeError(f"every must be a positive number of clouds, got {every}")
    refine = tuple(dict.fromkeys(refine))
    if not refine:
        raise MapsqueezeError("refine: give at least one number of refinement steps (0: the paper's encoder)")
    for steps in refine:
        check_refine_steps(steps)
    variants = build_variants(codecs, models or [], precision, log, refine, device)
    out_dir.mkdir(parents=True, exist_ok=True)
    arguments = {"inputs": [str(p) for p in inputs], "codecs": codecs, "models": models, "precision": precision,
                 "split": split, "refine": list(refine), "every": every, "fresh": fresh, "device": device}
    record = run_record(arguments, variants)
    _write_json(record, out_dir / "run.json")
    rows: list[Row] = [] if fresh else reusable_rows(read_rows(out_dir / "results.csv"), variants, log)
    done = {r.key() for r in rows}
    for cloud in collect_clouds(inputs, split, every):
        todo = [v for v in variants if (cloud.name, *v.key()) not in done]
        if not todo:
            continue
        normals = normals_pca(cloud.points)
        for v in todo:
            if progress:
                progress(f"{cloud.name}: {v.codec} {v.setting}")
            t0 = time.perf_counter()
            data = v.encode(cloud.points, cloud.origin)
            t1 = time.perf_counter()
            decoded = v.decode(data, cloud.origin)
            t2 = time.perf_counter()
            m = evaluate(cloud.points, decoded, n_bytes=len(data), gt_normals=normals)
            if on_decoded:
                on_decoded(cloud.name, v.codec, v.setting, data, cloud.points, decoded, m)
            rows.append(Row(cloud.name, v.codec, v.setting, v.weights, len(cloud.points), len(data), m.bpp, m.d_e,
                            m.d_perp, m.iou, m.n_rec, t1 - t0, t2 - t1))
        write_rows(rows, out_dir / "results.csv")
        write_reports(rows, out_dir, final=False)  # progress so far
    if not rows:
        raise MapsqueezeError("nothing to benchmark (no clouds or no available codec)")
    write_rows(rows, out_dir / "results.csv")
    write_reports(rows, out_dir)
    record["finished"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    _write_json(record, out_dir / "run.json")
    return rows
