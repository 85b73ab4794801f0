"""Rate-distortion benchmark: every codec and setting on every cloud -> CSV, markdown table, plots.

mapsqueeze itself runs through the same `mapsqueeze.compress` / `mapsqueeze.decompress` calls as the CLI.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.shared import reference_checkpoints_dir

CLASSICAL = ("draco", "octree", "octree-ac", "gpcc")
PER_CLOUD_PLOTS_UP_TO = 6  # benchmarks of at most this many clouds also get one rd_<cloud>.png per cloud
SIZE_BANDS = (20_000, 50_000)
"""Cloud sizes (points) separating the bands of `size_band_comparison`: a 40 m submap of one 32-beam sweep has
~12k points, one 64/128-beam scan 30-60k, an aggregated map 50-250k."""


@dataclass
class Row:
    cloud: str
    codec: str
    setting: str
    n_points: int
    n_bytes: int
    bpp: float
    d_e: float
    d_perp: float
    iou: float
    n_decoded: int
    encode_s: float
    decode_s: float


@dataclass
class Cloud:
    name: str
    points: np.ndarray  # (N, 3) float64 world metres
    origin: np.ndarray  # lower corner of its box: mapsqueeze tiles start here


def collect_clouds(inputs: list[Path], split: str = "test", every: int = 1) -> Iterator[Cloud]:
    """Clouds from dataset folders (the given split), plain folders (every cloud file) and single files; with
    every=N only the first, (N+1)-th, ... of them (the others are not read)."""
    from mapsqueeze.data.mapping import MANIFEST_NAME, read_dataset
    from mapsqueeze.io import point_cloud_files, read_points

    def sources() -> Iterator[tuple[str, Callable[[], tuple[np.ndarray, np.ndarray]]]]:
        """(name, loader of (points, origin)) of every cloud, nothing read yet."""
        for path in inputs:
            if (path / MANIFEST_NAME).is_file():
                for record in read_dataset(path).split(split):
                    yield f"{path.name}/{record.path.stem}", lambda r=record: (r.load().points, r.bounds[0])
            else:
                files = point_cloud_files(path) if path.is_dir() else [path]
                for file in files:
                    yield file.stem, lambda f=file: _points_and_corner(read_points(f))

    for position, (name, load) in enumerate(sources()):
        if position % every == 0:
            yield Cloud(name, *load())


def _points_and_corner(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return points, points.min(axis=0)


@dataclass
class Variant:
    """One codec at one setting: encode(points, origin) -> bytes and decode(bytes) -> points."""

    codec: str
    setting: str
    encode: Callable[[np.ndarray, np.ndarray], bytes]
    decode: Callable[[bytes], np.ndarray]


def _learned_variants(codec: str, models: dict[str, object], precision: str, refine_steps: int = 0
                      ) -> list[Variant]:
    """One variant per model; with refine_steps the setting reads e.g. "e1,q+refine20"."""
    from mapsqueeze.api import compress, decompress

    label = f"{precision}+refine{refine_steps}" if refine_steps else precision
    return [Variant(codec, f"{name},{label}",
                    lambda pts, origin, m=model: compress(pts, model=m, precision=precision, refine_steps=refine_steps),
                    lambda data, m=model: decompress(data, model=m))
            for name, model in models.items()]


def state_sha256(network) -> str:
    """SHA-256 of a network's tensors (identifies an in-memory model such as an imported reference)."""
    import hashlib

    digest = hashlib.sha256()
    for key, value in sorted(network.state_dict().items()):
        digest.update(key.encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def unique_labels(names: list[str]) -> list[str]:
    """Shortest path suffixes that tell the models apart: runs/a/best, runs/b/best -> a/best, b/best (a training
    run's generic best/ or last/ folder always keeps its run's name)."""
    parts = [Path(n).parts or (n,) for n in names]
    depth = 2 if any(p[-1] in ("best", "last") and len(p) > 1 for p in parts) else 1
    while depth < max(map(len, parts)) and len({p[-depth:] for p in parts}) < len(parts):
        depth += 1
    return ["/".join(p[-depth:]) for p in parts]


def build_variants(codecs: list[str], models: list[str], precision: str, log: Callable[[str], None],
                   refine: tuple[int, ...] = (0,)) -> list[Variant]:
    """Every (codec, setting) to run; unavailable codecs are skipped with a message. The learned codecs run at each
    number of encode-time refinement steps in `refine` (depoco-ref's paper-mode f16 only without refinement)."""
    from mapsqueeze.baselines import BASELINES, get_baseline, setting_label
    from mapsqueeze.model import import_reference, load_model, shipped_models
    from mapsqueeze.model.autoencoder import CompressionModel

    variants: list[Variant] = []
    for codec in codecs:
        if codec == "mapsqueeze":
            names = models or shipped_models()
            if not names:
                log("mapsqueeze: no shipped model; pass --models DIR,... (skipped)")
            loaded = dict(zip(unique_labels(names), map(load_model, names)))
            for steps in refine:
                variants += _learned_variants(codec, loaded, precision, steps)
        elif codec == "depoco-ref":
            reference_dir = reference_checkpoints_dir()
            refs = sorted(p for p in reference_dir.glob("e[0-3]") if (p / "enc_best.pth").is_file())
            if not refs:
                log(f"depoco-ref: reference checkpoints not found in {reference_dir} (skipped)")
            loaded = {}
            for p in refs:
                network = import_reference(p)
                loaded[p.name] = CompressionModel(network, f"depoco-{p.name}", state_sha256(network))
            # the paper's float16 embeddings, and the same networks through our entropy-coded q embeddings
            if 0 in refine:
                for ref_precision in dict.fromkeys(("f16", precision)):
                    variants += _learned_variants(codec, loaded, ref_precision)
            for steps in refine:
                if steps:
                    variants += _learned_variants(codec, loaded, precision, steps)
        elif codec in BASELINES:
            baseline = get_baseline(codec)
            if not baseline.available():
                log(f"{codec}: unavailable ({baseline.requirement}) (skipped)")
                continue
            for setting in baseline.settings():
                variants.append(Variant(codec, setting_label(setting),
                                        lambda pts, origin, b=baseline, s=setting: b.encode(pts - origin, s),
                                        lambda data, b=baseline: b.decode(data)))
        else:
            raise MapsqueezeError(f"unknown codec {codec!r} (mapsqueeze, depoco-ref, {', '.join(BASELINES)})")
    return variants


def run_benchmark(inputs: list[Path], codecs: list[str], out_dir: Path, models: list[str] | None = None,
                  precision: str = "q", split: str = "test", log: Callable[[str], None] = print,
                  progress: Callable[[str], None] | None = None, fresh: bool = False,
                  refine: tuple[int, ...] = (0,), every: int = 1) -> list[Row]:
    """Run every variant on every cloud; write results.csv, results.md, rd.png (+ rd_<cloud>.png) into out_dir.

    Results already in out_dir/results.csv are kept and their (cloud, codec, setting) not run again, so a long
    benchmark can be resumed or extended by more codecs later; fresh=True starts over. refine: the encode-time
    refinement steps the learned codecs run at (each a setting of its own). every=N runs on every N-th cloud only
    (the first, the (N+1)-th, ...; names unchanged, so a subset can be added to a full run's folder).
    """
    from mapsqueeze.geometry.normals import normals_pca
    from mapsqueeze.metrics import evaluate

    from mapsqueeze.codec.compress import check_refine_steps

    if every < 1:
        raise MapsqueezeError(f"every must be a positive number of clouds, got {every}")
    refine = tuple(dict.fromkeys(refine))
    if not refine:
        raise MapsqueezeError("refine: give at least one number of refinement steps (0: the paper's encoder)")
    for steps in refine:
        check_refine_steps(steps)
    out_dir.mkdir(parents=True, exist_ok=True)
    variants = build_variants(codecs, models or [], precision, log, refine)
    rows: list[Row] = [] if fresh else read_results(out_dir / "results.csv")
    done = {(r.cloud, r.codec, r.setting) for r in rows}
    for cloud in collect_clouds(inputs, split, every):
        todo = [v for v in variants if (cloud.name, v.codec, v.setting) not in done]
        if not todo:
            continue
        normals = normals_pca(cloud.points)
        for v in todo:
            if progress:
                progress(f"{cloud.name}: {v.codec} {v.setting}")
            t0 = time.perf_counter()
            data = v.encode(cloud.points, cloud.origin)
            t1 = time.perf_counter()
            decoded = v.decode(data)
            t2 = time.perf_counter()
            if v.codec in CLASSICAL:
                decoded = decoded + cloud.origin
            m = evaluate(cloud.points, decoded, n_bytes=len(data), gt_normals=normals)
            rows.append(Row(cloud.name, v.codec, v.setting, len(cloud.points), len(data), m.bpp, m.d_e, m.d_perp,
                            m.iou, m.n_rec, t1 - t0, t2 - t1))
        write_results(rows, out_dir, per_cloud_plots=False)  # progress so far; plots per cloud at the end
    if not rows:
        raise MapsqueezeError("nothing to benchmark (no clouds or no available codec)")
    write_results(rows, out_dir)
    return rows


def read_results(path: Path) -> list[Row]:
    """Rows of an earlier results.csv (none when absent)."""
    if not path.is_file():
        return []
    types = {name: field.type for name, field in Row.__dataclass_fields__.items()}
    casts = {"str": str, "int": int, "float": float}
    with open(path, newline="") as f:
        try:
            return [Row(**{k: casts[types[k]](v) for k, v in record.items()}) for record in csv.DictReader(f)]
        except (KeyError, TypeError, ValueError) as exc:
            raise MapsqueezeError(f"{path}: not a results.csv of this version ({exc}); use --fresh") from None


def summarise(rows: list[Row]) -> list[dict]:
    """Mean of every metric per (codec, setting) over the clouds."""
    groups: dict[tuple[str, str], list[Row]] = {}
    for r in rows:
        groups.setdefault((r.codec, r.setting), []).append(r)
    out = []
    for (codec, setting), rs in groups.items():
        out.append({"codec": codec, "setting": setting, "clouds": len(rs),
                    **{k: float(np.mean([getattr(r, k) for r in rs]))
                       for k in ("bpp", "d_e", "d_perp", "iou", "encode_s", "decode_s")}})
    return sorted(out, key=lambda s: (s["codec"], s["bpp"]))


def classical_d_e_at(summary: list[dict], bpp: float) -> float:
    """D_e of the best classical codec at this bpp (Pareto front of all classical settings, log-bpp interpolation)."""
    from mapsqueeze.baselines.rd import distortion_at

    classical = [s for s in summary if s["codec"] in CLASSICAL]
    if not classical:
        return float("nan")
    return float(distortion_at([s["bpp"] for s in classical], [s["d_e"] for s in classical], bpp))


def write_results(rows: list[Row], out_dir: Path, per_cloud_plots: bool = True) -> None:
    """results.csv, results.md and rd.png; per_cloud_plots adds rd_<cloud>.png for small benchmarks."""
    from mapsqueeze.io import atomic_output

    with atomic_output(out_dir / "results.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(asdict(rows[0])))
        writer.writeheader()
        writer.writerows(asdict(r) for r in rows)
    summary = summarise(rows)
    comparison = per_cloud_comparison(rows)
    wins: dict[tuple[str, str], list[bool]] = {}
    for r, reference in comparison:
        if not np.isnan(reference):
            wins.setdefault((r.codec, r.setting), []).append(bool(r.d_e < reference))
    lines = ["| codec | setting | clouds | bpp | D_e (m) | D_perp (m) | IoU | encode (s) | decode (s) | "
             "best classical D_e at this bpp (m) | beats the classical front on (clouds) |", "|---" * 11 + "|"]
    for s in summary:
        ref, won = "", ""
        if s["codec"] not in CLASSICAL:
            ref = f"{classical_d_e_at(summary, s['bpp']):.4f}"
            outcome = wins.get((s["codec"], s["setting"]), [])
            won = f"{sum(outcome)} / {len(outcome)}"
        lines.append(f"| {s['codec']} | {s['setting']} | {s['clouds']} | {s['bpp']:.4f} | {s['d_e']:.4f} | "
                     f"{s['d_perp']:.4f} | {s['iou']:.3f} | {s['encode_s']:.2f} | {s['decode_s']:.2f} | {ref} | "
                     f"{won} |")
    lines += ["", "Per cloud: each learned setting against the classical Pareto front of the same cloud.", "",
              "| cloud | codec | setting | bpp | D_e (m) | best classical D_e at this bpp (m) | better |",
              "|---" * 7 + "|"]
    for r, reference in comparison:
        lines.append(f"| {r.cloud} | {r.codec} | {r.setting} | {r.bpp:.4f} | {r.d_e:.4f} | {reference:.4f} | "
                     f"{'outside front' if np.isnan(reference) else 'yes' if r.d_e < reference else 'no'} |")
    lines += size_band_comparison(comparison)
    lines += reference_comparison(rows)
    with atomic_output(out_dir / "results.md") as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    plot_rd(summary, out_dir / "rd.png", f"mean over {len({r.cloud for r in rows})} clouds")
    clouds = sorted({r.cloud for r in rows})
    if per_cloud_plots and len(clouds) <= PER_CLOUD_PLOTS_UP_TO:
        for cloud in clouds:
            plot_rd(summarise([r for r in rows if r.cloud == cloud]), out_dir / f"rd_{Path(cloud).name}.png", cloud)


def size_band_comparison(comparison: list[tuple[Row, float]]) -> list[str]:
    """Markdown lines: each learned setting's mean D_e change against the classical front, and its wins, per band
    of cloud size (SIZE_BANDS; sparse clouds are where the learned codecs lose)."""
    edges = (0, *SIZE_BANDS, np.inf)
    bands = [f"{lo:,} - {hi:,}" if np.isfinite(hi) else f">= {lo:,}" for lo, hi in zip(edges, edges[1:])]
    changes: dict[tuple[str, str], list[list[float]]] = {}
    for r, reference in comparison:
        if not np.isnan(reference):
            band = int(np.searchsorted(SIZE_BANDS, r.n_points, side="right"))
            changes.setdefault((r.codec, r.setting), [[] for _ in bands])[band].append(r.d_e / reference - 1)
    if not changes:
        return []
    lines = ["", "By cloud size: mean D_e change against the classical front at the same bpp (clouds better / "
             "clouds) per band of points in the cloud.", "",
             "| codec | setting | " + " | ".join(f"{band} points" for band in bands) + " |",
             "|---" * (2 + len(bands)) + "|"]
    for (codec, setting), per_band in sorted(changes.items()):
        cells = [f"{np.mean(c):+.1%} ({sum(v < 0 for v in c)} / {len(c)})" if c else "" for c in per_band]
        lines.append(f"| {codec} | {setting} | " + " | ".join(cells) + " |")
    return lines


def reference_comparison(rows: list[Row]) -> list[str]:
    """Markdown lines: each mapsqueeze row against the depoco-ref front on the same cloud at the same bpp, once as
    published (f16 embeddings) and once through every precision (our q coding of the reference networks)."""
    published = [replace(r, codec="depoco-ref f16") for r in rows
                 if r.codec == "depoco-ref" and r.setting.endswith(",f16")]
    against_published = per_cloud_comparison(rows + published, ("depoco-ref f16",), ("mapsqueeze",))
    against_all = per_cloud_comparison(rows, ("depoco-ref",), ("mapsqueeze",))
    if all(np.isnan(ref) for _, ref in against_all):
        return []

    def cells(d_e: float, ref: float) -> str:
        return "outside its bpp range | |" if np.isnan(ref) else f"{ref:.4f} | {d_e / ref - 1:+.1%} |"

    lines = ["", "Per cloud: mapsqueeze against the front of depoco-ref (the reference checkpoints) on the same cloud, "
             "interpolated in log bpp: as published (f16 embeddings), and through every precision (with our q).", "",
             "| cloud | setting | bpp | D_e (m) | depoco-ref f16 D_e at this bpp (m) | change | "
             "depoco-ref (f16, q) D_e at this bpp (m) | change |", "|---" * 8 + "|"]
    for (r, ref_published), (_, ref_all) in zip(against_published, against_all):
        lines.append(f"| {r.cloud} | {r.setting} | {r.bpp:.4f} | {r.d_e:.4f} | {cells(r.d_e, ref_published)} "
                     f"{cells(r.d_e, ref_all)}")
    return lines


def per_cloud_comparison(rows: list[Row], front_codecs: tuple[str, ...] = CLASSICAL,
                         codecs: tuple[str, ...] | None = None) -> list[tuple[Row, float]]:
    """(row, D_e of the Pareto front of front_codecs' rows on the same cloud at the same bpp) for every row of
    `codecs` (default: every codec not in front_codecs).

    The front is interpolated in log bpp (NaN when the cloud has no row of front_codecs)."""
    from mapsqueeze.baselines.rd import distortion_at

    fronts: dict[str, list[Row]] = {}
    for r in rows:
        if r.codec in front_codecs:
            fronts.setdefault(r.cloud, []).append(r)
    out = []
    for r in rows:
        if r.codec in front_codecs or (codecs is not None and r.codec not in codecs):
            continue
        front = fronts.get(r.cloud, [])
        reference = (float(distortion_at([c.bpp for c in front], [c.d_e for c in front], r.bpp))
                     if front else float("nan"))
        out.append((r, reference))
    return out


def series_name(result: dict) -> str:
    """Plot line of a result: the classical codec, or a learned codec at one embedding precision ("mapsqueeze q")."""
    if result["codec"] in CLASSICAL:
        return result["codec"]
    return f"{result['codec']} {result['setting'].rsplit(',', 1)[-1]}"


def plot_rd(summary: list[dict], path: Path, title: str) -> None:
    """D_e, D_perp and IoU against bpp (log x), one line per codec (means over clouds) -> PNG at path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mapsqueeze.baselines.rd import pareto_front
    from mapsqueeze.io import atomic_output

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, key, label in zip(axes, ("d_e", "d_perp", "iou"), ("D_e (m)", "D_perp (m)", "IoU")):
        for codec in sorted({series_name(s) for s in summary}):
            pts = [s for s in summary if series_name(s) == codec]
            bpp = np.array([s["bpp"] for s in pts])
            val = np.array([s[key] for s in pts])
            if codec in CLASSICAL and len(pts) > 2:  # show the codec's Pareto front, not every setting
                front = pareto_front(bpp, val if key != "iou" else -val)
                bpp, val = bpp[front], val[front]
            order = np.argsort(bpp)
            ax.plot(bpp[order], val[order], marker="o", label=codec)
        ax.set_xscale("log")
        ax.set_xlabel("bits per point")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
