"""`mapsqueeze simulate`: procedural LiDAR maps -> a submap dataset like `build-map` writes."""

import time
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from mapsqueeze.cli.app import app, make_console
from mapsqueeze.data.simulator.presets import PRESETS
from mapsqueeze.data.simulator.sensors import SENSORS
from mapsqueeze.errors import SimulationError


def _names(text: str, option: str) -> tuple[str, ...]:
    names = tuple(part.strip() for part in text.split(",") if part.strip())
    if not names:
        raise SimulationError(f"{option}: give at least one name")
    return names


def _scan_range(text: str) -> tuple[int, int]:
    """'1-100' -> (1, 100); '6' -> (6, 6)."""
    low, _, high = text.partition("-")
    try:
        bounds = (int(low), int(high or low))
    except ValueError:
        raise SimulationError(f"--scans: expected MIN-MAX or N (whole numbers), got {text!r}") from None
    return bounds


@app.command("simulate")
def simulate(
    out_dir: Path = typer.Option(..., "-o", "--out", help="Dataset directory: one PLY per submap + manifest.json."),
    sensor: str = typer.Option("hdl64", "--sensor", help=f"Sensor model(s), comma-separated; each scene draws one "
                               f"(repeat a name to draw it more often): {', '.join(SENSORS)}."),
    preset: str = typer.Option("urban", "--preset", help=f"Scene preset(s), comma-separated; each scene draws one "
                               f"(repeat a name to draw it more often): {', '.join(PRESETS)}."),
    submaps: int = typer.Option(200, "--submaps", min=1, help="Number of submaps to simulate."),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed and options give the same dataset."),
    scans: str = typer.Option("1-100", "--scans", help="Scans aggregated per submap: MIN-MAX (log-uniform) or N."),
    per_scene: int = typer.Option(5, "--per-scene", min=1, help="Submaps (15 m apart) per simulated scene."),
    workers: int = typer.Option(1, "--workers", min=1, help="Worker processes (scenes run in parallel)."),
    split: str = typer.Option("", "--split", help="Put every submap in this split (train, val or test); default: "
                              "every 10th scene to val, the rest to train. Simulating into an existing dataset "
                              "with another seed adds to it."),
) -> None:
    """Simulate LiDAR maps of procedural driving scenes and store them as a submap dataset.

    Scenes (roads, buildings, cars, vegetation, fences, poles, clutter, terrain) are ray-cast with a real sensor's
    beam pattern while driving; each submap aggregates a random number of scans with the real pipeline (2-20 m
    range, 10 cm voxels, 40 x 40 x 15 m boxes every 15 m). Every point carries its intensity (0..1), semantic
    label (SemanticKITTI ids) and instance id.
    """
    from mapsqueeze.data.simulator.simulate import SimulationConfig, simulate_dataset  # trimesh: imported here

    if out_dir.exists() and not out_dir.is_dir():
        raise SimulationError(f"{out_dir}: exists and is not a directory")
    config = SimulationConfig(n_submaps=submaps, sensors=_names(sensor, "--sensor"),
                              presets=_names(preset, "--preset"), seed=seed, submaps_per_scene=per_scene,
                              scans_per_submap=_scan_range(scans), split=split)
    console = make_console(stderr=True)
    start = time.perf_counter()
    columns = (TextColumn("simulating"), BarColumn(), MofNCompleteColumn(), TextColumn("submaps"),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console, disable=not console.is_terminal) as progress:
        task = progress.add_task("simulate", total=submaps)
        manifest = simulate_dataset(out_dir, config, workers, lambda n: progress.advance(task, n))
    minutes = (time.perf_counter() - start) / 60
    console.print(f"{submaps:,} submaps ({config.n_scenes:,} scenes) in {minutes:.1f} min -> {manifest}")
