"""Write MODEL_CARD.md for a shipped model: training provenance from its config plus bpp / D_e / D_perp / IoU of
the full codec (q precision; the paper's encoder and 20 steps of encode-time refinement) on each real submap in
the shared folder's data/real/submaps (see mapsqueeze.shared).

    .venv/bin/python benchmarks/model_card.py e1 [--log runs/e1/log.csv] [--provenance runs/e1/PROVENANCE.md]
"""

import argparse
from pathlib import Path

from mapsqueeze.api import compress, decompress
from mapsqueeze.io import atomic_write_bytes, read_points
from mapsqueeze.metrics import evaluate
from mapsqueeze.model import load_model
from mapsqueeze.model.shipped import SHIPPED_DIR
from mapsqueeze.shared import real_submaps_dir

REFINE_STEPS = (0, 20)  # the paper's encoder, and `compress --refine 20`


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("name")
    ap.add_argument("--log", type=Path, help="training log.csv to summarise")
    ap.add_argument("--provenance", type=Path, help="markdown file with the training commands, appended verbatim")
    args = ap.parse_args()
    model = load_model(args.name)
    c = model.config
    lines = [f"# Model card: {c.name}", "",
             f"- Rate point {c.name}: subsampling distance r_s = {c.subsampling_dist:g} m, decoder upsampling "
             f"{' x '.join(map(str, c.upsampling_factors))} = {c.native_upsampling} points per embedding point.",
             f"- Architecture: the paper's (docs/model.md); weights SHA-256 `{model.weights_sha256}`.",
             "- Training: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                        for k, v in c.extra.items()),
             "- Training data: simulated maps only (mapsqueeze simulate, docs/simulator.md); the real submaps below "
             "were never used for training or model selection.", ""]
    if args.log and args.log.is_file():
        rows = args.log.read_text().strip().splitlines()
        lines += ["Training log (last epochs):", "", "```", rows[0], *rows[1:][-5:], "```", ""]
    lines += ["## Real submaps (full codec, precision q)", "",
              "| submap | points | encoding | bytes | bpp | D_e (m) | D_perp (m) | IoU |",
              "|---|---|---|---|---|---|---|---|"]
    for path in sorted(real_submaps_dir().glob("*.ply")):
        gt = read_points(path)
        for steps in REFINE_STEPS:
            data = compress(gt, model=model, refine_steps=steps)
            m = evaluate(gt, decompress(data, model=model), n_bytes=len(data))
            encoding = f"refine {steps}" if steps else "paper"
            lines.append(f"| {path.stem} | {len(gt):,} | {encoding} | {len(data):,} | {m.bpp:.4f} | {m.d_e:.4f} | "
                         f"{m.d_perp:.4f} | {m.iou:.3f} |")
    lines += ["", f"Command: `.venv/bin/python benchmarks/model_card.py {args.name}"
              + (f" --log {args.log}" if args.log else "")
              + (f" --provenance {args.provenance}" if args.provenance else "") + "`"]
    if args.provenance:
        lines += ["", "## Provenance", "", args.provenance.read_text().strip()]
    atomic_write_bytes(SHIPPED_DIR / args.name / "MODEL_CARD.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
