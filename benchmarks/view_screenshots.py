"""Screenshots of `mapsqueeze view` pages for README.md and docs/viewer.md (docs/figures/view_*.png).

Two maps, each compressed with the shipped model and shown over its original: the real KITTI submap (one tile) and
the `make demo` simulated street map (UTM coordinates, several tiles). The pages go to --out (kept for a look in a
browser); the screenshots are taken with the same headless Chromium call as the test suite
(mapsqueeze.view.browser.screenshot).

    .venv/bin/python benchmarks/view_screenshots.py --model e1 --out results/view --figures docs/figures
"""

import argparse
from pathlib import Path

import mapsqueeze
from mapsqueeze.demo import simulated_map
from mapsqueeze.shared import real_submaps_dir
from mapsqueeze.view import CloudInput, ViewInput, load_cloud, write_view
from mapsqueeze.view.browser import screenshot

SHOTS = {  # figure name suffix -> the page's URL fragment (view state)
    "kitti": {"side": "color=cloud&layout=side", "error": "color=error&size=2.5"},
    "multitile": {"tiles": "color=height&tiles=1&embedding=1&view=top&size=1.5", "error": "color=error&tiles=1"},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="e1")
    parser.add_argument("--out", type=Path, default=Path("results/view"))
    parser.add_argument("--figures", type=Path, default=Path("docs/figures"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    args.figures.mkdir(parents=True, exist_ok=True)
    kitti = real_submaps_dir() / "kitti_hdl64_6scans.ply"
    originals = {"kitti": load_cloud(kitti), "multitile": CloudInput(simulated_map())}
    for name, original in originals.items():
        data = mapsqueeze.compress(original.points, model=args.model)
        (args.out / f"{name}.msq").write_bytes(data)
        page = args.out / f"{name}.html"
        scene = write_view(ViewInput(f"{name}.msq ({args.model})", data, original=original), page)
        summary = scene["summary"]
        print(f"{name}: {summary['points']:,} points, {len(scene['tiles'])} tiles, {summary['fileBytes']:,} bytes, "
              f"{summary['bpp']:.4f} bpp, D_e {summary['dE']:.4f} m, page {page.stat().st_size:,} bytes")
        for suffix, fragment in SHOTS[name].items():
            png = screenshot(page, args.figures / f"view_{name}_{suffix}.png", fragment, size=(1200, 800))
            print(f"  {png}")


if __name__ == "__main__":
    main()
