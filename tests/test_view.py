"""`mapsqueeze view`: the tile listing of the API, the page's data, the CLI, and the page rendered in headless Chromium.

A small randomly initialised model (8 x 8 x 4 m tiles) keeps the network fast; the viewer does not care whether the
weights are trained. The browser test needs Chromium (`apt-get install chromium`, which .ci/run does): skipped without
it, except in CI (CI=true or MAPSQUEEZE_REQUIRE_SHARED=1), where its absence fails.
"""

import base64
import csv
import json
import os
import re

import numpy as np
import pytest
from scipy.spatial import cKDTree

import mapsqueeze
from mapsqueeze.codec.compress import AttributeOptions
from mapsqueeze.codec.container import open_container
from mapsqueeze.codec.decompress import decode_embedding
from mapsqueeze.errors import ContainerError
from mapsqueeze.geometry.morton import coarse_to_fine_subset
from mapsqueeze.io import write_points
from mapsqueeze.metrics import evaluate
from mapsqueeze.model import load_model
from mapsqueeze.view import CloudInput, ViewInput, build_scene, load_cloud, render_page, write_view
from mapsqueeze.view.browser import find_chromium, screenshot

UTM = np.array([500_000.0, 4_000_000.0, 50.0])


@pytest.fixture(scope="module")
def model_dir(tiny_model_dir):
    return tiny_model_dir


@pytest.fixture(scope="module")
def map_points():
    """A 16 x 8 m ground with a wall (three network tiles) and a sparse post 12 m away (a raw tile), in UTM."""
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(0, 16, 5000), rng.uniform(0, 8, 5000), rng.normal(0.5, 0.03, 5000)]
    wall = np.c_[rng.uniform(1, 15, 1500), rng.normal(6.0, 0.02, 1500), rng.uniform(0.5, 3.5, 1500)]
    post = np.c_[rng.normal(28, 0.05, 4), rng.normal(1, 0.05, 4), rng.uniform(0.5, 3.5, 4)]
    return np.concatenate([ground, wall, post]) + UTM


@pytest.fixture(scope="module")
def compressed(map_points, model_dir):
    return mapsqueeze.compress(map_points, model=model_dir, fallback=False)  # network tiles, as the model is untrained


def smooth_intensity(points: np.ndarray) -> np.ndarray:
    """An intensity that varies smoothly over the map (about 0 to 350): decoded points near an original point should
    get about its value."""
    local = points - UTM
    return (10.0 * local[:, 0] + 20.0 * local[:, 2]).astype(np.float32)


@pytest.fixture(scope="module")
def intensity_files(tmp_path_factory, map_points, model_dir):
    """map.ply (points with smooth_intensity) and map.msq, its compression with the intensity coded finely (0.25 m
    voxels, step 1/256 of the range: the page must show the decoded values, which then follow the original's)."""
    folder = tmp_path_factory.mktemp("intensity")
    write_points(folder / "map.ply", map_points, attributes={"intensity": smooth_intensity(map_points)})
    mapsqueeze.compress_file(folder / "map.ply", folder / "map.msq", model=model_dir,
                             attribute_options=AttributeOptions(voxel_m=0.25, relative_step=1 / 256))
    return folder / "map.ply", folder / "map.msq"


def unpack(b64: str, count: int, width: int = 1) -> np.ndarray:
    values = np.frombuffer(base64.b64decode(b64), dtype="<u2").astype(np.float64)
    assert len(values) == count * width
    return values.reshape(count, width) if width > 1 else values


def scene_of_page(page: str) -> dict:
    return json.loads(re.search(r'<script type="application/json" id="scene-data">(.*?)</script>', page,
                                re.S).group(1))


def test_tiles_lists_modes_and_embeddings(compressed):
    tiles = mapsqueeze.tiles(compressed)
    assert [t.coding for t in tiles].count("raw") == 1 and [t.coding for t in tiles].count("network") == 3
    reader, stream = open_container(compressed)
    with stream:
        for position, tile in enumerate(tiles):
            assert tile.payload_bytes == reader.entries[position].length
            if tile.coding == "raw":
                assert tile.model_id is None and tile.embedding.shape == (0, 3)
                with pytest.raises(ContainerError, match="holds no embedding"):
                    decode_embedding(reader, position)
            else:
                assert tile.model_id == reader.header.model_id
                assert len(tile.embedding) == len(decode_embedding(reader, position)[0]) > 0
                # embedding points lie in the tile's points box in world coordinates (to q's centimetre steps)
                inside = (tile.embedding >= tile.bounds[0] - 0.02) & (tile.embedding <= tile.bounds[1] + 0.02)
                assert inside.all()
            assert (tile.cell[0] <= tile.bounds[0] + 1e-9).all() and (tile.bounds[1] <= tile.cell[1] + 1e-9).all()
    assert sum(t.n_points for t in tiles) == mapsqueeze.info(compressed).n_points


def test_scene_holds_the_subsets_errors_and_tiles(compressed, map_points, model_dir):
    original = CloudInput(map_points, intensity=np.linspace(0, 255, len(map_points)))
    scene = build_scene(ViewInput("tiny", compressed, original=original, model=model_dir), max_points=3000)
    decoded = mapsqueeze.decompress(compressed, model=model_dir)
    low, size, centre = np.array(scene["box"]["low"]), np.array(scene["box"]["size"]), np.array(scene["centre"])
    clouds = {c["name"]: c for c in scene["clouds"]}
    assert clouds["original"]["total"] == len(map_points) and clouds["decoded"]["total"] == len(decoded)
    for name, full, other in (("original", map_points, decoded), ("decoded", decoded, map_points)):
        cloud = clouds[name]
        assert cloud["drawn"] == 3000
        world = centre + low + unpack(cloud["positions"], 3000, 3) / 65535 * size
        # every drawn point is one of the cloud's own (to the quantisation step) ...
        step = np.linalg.norm(size / 65535)
        assert cKDTree(full).query(world)[0].max() <= step
        # ... and its error is its distance to the nearest point of the whole other cloud
        error = unpack(cloud["error"], 3000) / 65535 * scene["errorMax"]
        np.testing.assert_allclose(error, cKDTree(other).query(world)[0], atol=2 * step + scene["errorMax"] / 65535)
        assert cloud["intensity"] is None  # the decoded map has no intensity: not offered, not even the original's
    assert scene["intensityRange"] is None
    assert 0 < scene["errorDefault"] <= scene["errorMax"]
    assert scene["embedding"]["count"] == sum(len(t.embedding) for t in mapsqueeze.tiles(compressed))
    assert sorted(t["coding"] for t in scene["tiles"]) == ["network", "network", "network", "raw"]
    metrics = evaluate(map_points, decoded, n_bytes=len(compressed))
    assert scene["summary"]["dE"] == pytest.approx(metrics.d_e) and scene["summary"]["iou"] == pytest.approx(metrics.iou)
    assert scene["summary"]["bpp"] == pytest.approx(8 * len(compressed) / len(map_points))


def test_intensity_is_shown_when_the_decoded_map_has_it(compressed, map_points):
    decoded = CloudInput(map_points[::2], intensity=np.arange(len(map_points[::2]), dtype=float))
    scene = build_scene(ViewInput("tiny", compressed, decoded=decoded), max_points=500)
    drawn = decoded.intensity[coarse_to_fine_subset(decoded.points, 500)]  # the drawn points' own intensities
    assert scene["intensityRange"] == [drawn.min(), drawn.max()]
    (cloud,) = scene["clouds"]
    assert cloud["name"] == "decoded" and cloud["error"] is None and scene["summary"]["dE"] is None
    expected = (drawn - drawn.min()) / (drawn.max() - drawn.min()) * 65535
    np.testing.assert_allclose(unpack(cloud["intensity"], 500), expected, atol=0.5)


def test_page_shows_the_intensities_decoded_from_the_file(tmp_path, intensity_files, map_points, model_dir, run_cli):
    """A .msq with intensity: the page's decoded cloud carries the file's decoded intensities, close to the original's
    at nearby points, and the original cloud the original file's intensities."""
    ply, msq = intensity_files
    assert mapsqueeze.info(msq).attributes == ("intensity",)
    code, out, err = run_cli("view", str(msq), "--original", str(ply), "-o", str(tmp_path / "v.html"),
                             "--max-points", "3000", "--model", str(model_dir))
    assert code == 0, err
    scene = scene_of_page((tmp_path / "v.html").read_text())
    low, size, centre = np.array(scene["box"]["low"]), np.array(scene["box"]["size"]), np.array(scene["centre"])
    (lowest, highest), original_intensity = scene["intensityRange"], smooth_intensity(map_points)
    clouds = {c["name"]: c for c in scene["clouds"]}
    drawn = {}
    for name, cloud in clouds.items():
        world = centre + low + unpack(cloud["positions"], cloud["drawn"], 3) / 65535 * size
        drawn[name] = world, lowest + unpack(cloud["intensity"], cloud["drawn"]) / 65535 * (highest - lowest)
    step = (highest - lowest) / 65535
    # the original's are the file's own
    world, intensity = drawn["original"]
    np.testing.assert_allclose(intensity, original_intensity[cKDTree(map_points).query(world)[1]], atol=step)
    # the decoded ones are the file's decoded intensities, which match the original's at the nearest original point
    decoded = mapsqueeze.decompress_cloud(msq, model=model_dir)
    world, intensity = drawn["decoded"]
    np.testing.assert_allclose(intensity, decoded.attributes["intensity"][cKDTree(decoded.points).query(world)[1]],
                               atol=step + 1e-3)
    error = np.abs(intensity - original_intensity[cKDTree(map_points).query(world)[1]]).mean()
    constant_guess = np.abs(original_intensity - np.median(original_intensity)).mean()
    assert error < 0.1 * constant_guess, (error, constant_guess)


def test_geometry_only_file_offers_no_intensity_colouring(tmp_path, compressed, intensity_files, model_dir, run_cli):
    """Without intensity in the .msq nothing is coloured by intensity, even when the original has it."""
    ply, _ = intensity_files
    (tmp_path / "map.msq").write_bytes(compressed)
    code, out, err = run_cli("view", str(tmp_path / "map.msq"), "--original", str(ply), "--max-points", "500",
                             "--model", str(model_dir))
    assert code == 0, err
    scene = scene_of_page((tmp_path / "map.html").read_text())
    assert scene["intensityRange"] is None and [c["intensity"] for c in scene["clouds"]] == [None, None]


def test_page_is_self_contained(compressed, map_points, model_dir):
    page = render_page(build_scene(ViewInput("a </script> name", compressed, original=CloudInput(map_points),
                                             model=model_dir), max_points=500))
    assert not re.search(r"https?://", page)  # nothing to fetch from anywhere
    assert "default-src 'none'" in page  # and the browser is told to refuse any request
    assert "<script src" not in page and "<link" not in page
    scene = scene_of_page(page)
    assert scene["name"] == "a </script> name" and len(scene["clouds"]) == 2


def test_load_cloud_keeps_intensity(tmp_path, map_points):
    write_points(tmp_path / "map.ply", map_points, attributes={"intensity": np.arange(len(map_points), dtype=np.float32)})
    cloud = load_cloud(tmp_path / "map.ply")
    np.testing.assert_array_equal(cloud.intensity, np.arange(len(map_points)))
    write_points(tmp_path / "plain.ply", map_points)
    assert load_cloud(tmp_path / "plain.ply").intensity is None
    local = map_points - UTM  # KITTI .bin: float32 coordinates, the intensity is called reflectance
    write_points(tmp_path / "scan.bin", local, attributes={"reflectance": np.linspace(0, 1, len(local))})
    np.testing.assert_allclose(load_cloud(tmp_path / "scan.bin").intensity, np.linspace(0, 1, len(local)), atol=1e-6)


def test_cli_writes_the_page_and_rejects_bad_input(tmp_path, compressed, map_points, model_dir, run_cli):
    msq = tmp_path / "map.msq"
    msq.write_bytes(compressed)
    write_points(tmp_path / "map.ply", map_points)
    code, out, err = run_cli("view", str(msq), "--original", str(tmp_path / "map.ply"), "--max-points", "2000",
                             "--model", str(model_dir))
    assert code == 0, err
    page = (tmp_path / "map.html").read_text()
    assert [c["drawn"] for c in scene_of_page(page)["clouds"]] == [2000, 2000]
    for args, message in (
        (["view", str(tmp_path / "missing.msq")], "no such file"),
        (["view", str(tmp_path / "map.ply")], "not a .msq container"),
        (["view", str(msq), "--original", str(tmp_path / "missing.ply")], "no such file"),
        (["view", str(msq), "-o", str(tmp_path / "no" / "view.html")], "does not exist"),
        (["view", str(msq), "-o", str(tmp_path)], "is a directory"),
        (["view", str(msq), "--max-points", "0"], "--max-points"),
    ):
        code, out, err = run_cli(*args)
        assert code == 2 and err.startswith("error: ") and message in err and err.count("\n") == 1, (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.html", "map.msq", "map.ply"]  # nothing half-written


def test_cli_open_hands_the_page_to_the_browser(tmp_path, compressed, model_dir, run_cli, monkeypatch):
    import webbrowser

    opened = []
    monkeypatch.setattr(webbrowser, "open", opened.append)
    (tmp_path / "map.msq").write_bytes(compressed)
    code, out, err = run_cli("view", str(tmp_path / "map.msq"), "-o", str(tmp_path / "v.html"), "--open",
                             "--max-points", "100", "--model", str(model_dir))
    assert code == 0, err
    assert opened == [(tmp_path / "v.html").resolve().as_uri()]


@pytest.mark.slow
def test_bench_writes_a_report_with_a_view_per_cloud(tmp_path, map_points, model_dir, run_cli):
    (tmp_path / "clouds").mkdir()
    write_points(tmp_path / "clouds" / "street.ply", map_points)
    write_points(tmp_path / "clouds" / "shifted.ply", map_points[::2] + [3.0, 0.0, 0.0])
    code, out, err = run_cli("bench", str(tmp_path / "clouds"), "--codecs", "octree,mapsqueeze", "--models",
                             str(model_dir), "-o", str(tmp_path / "out"))
    assert code == 0, err
    report = (tmp_path / "out" / "report.html").read_text()
    assert '<img src="rd.png"' in report and '<img src="rd_street.png"' in report
    with open(tmp_path / "out" / "results.csv") as f:
        rows = {r["cloud"]: r for r in csv.DictReader(f) if r["codec"] == "mapsqueeze"}
    for cloud in ("street", "shifted"):
        assert report.count(f'<a href="views/{cloud}.html">') == 1
        scene = scene_of_page((tmp_path / "out" / "views" / f"{cloud}.html").read_text())
        assert scene["name"] == f"{cloud} (mapsqueeze {rows[cloud]['setting']})"
        assert scene["summary"]["dE"] == pytest.approx(float(rows[cloud]["d_e"]))  # the row's own result


def _require_chromium():
    """Skip without Chromium, but fail in CI (CI=true or MAPSQUEEZE_REQUIRE_SHARED=1) unless .ci/run, outside CI and
    without root to install it, said to skip (MAPSQUEEZE_NO_BROWSER=1)."""
    if find_chromium() is None:
        in_ci = os.environ.get("CI") == "true" or os.environ.get("MAPSQUEEZE_REQUIRE_SHARED") == "1"
        if in_ci and os.environ.get("MAPSQUEEZE_NO_BROWSER") != "1":
            pytest.fail("chromium is required in CI (.ci/run installs it: apt-get install chromium)")
        pytest.skip("chromium not installed (apt-get install chromium): the page is not rendered")


def _near(image: np.ndarray, rgb, tolerance: int = 40) -> np.ndarray:
    return (np.abs(image[..., :3].astype(int) - np.array(rgb)).max(axis=-1) <= tolerance)


PANEL_PX = 360  # the summary panel on the right of the page (viewer.css)
ORIGINAL_RGB, DECODED_RGB = (77, 163, 255), (255, 140, 26)  # CLOUD_COLORS of viewer.js
BACKGROUND_RGB = (16, 19, 24)
ERROR_RAMP = ((0, (0.15, 0.3, 1.0)), (0.25, (0.1, 0.85, 0.9)), (0.5, (0.3, 0.9, 0.3)), (0.75, (1.0, 0.9, 0.1)),
              (1, (0.95, 0.15, 0.1)))  # RAMPS.error of viewer.js: the colour of an error at a fraction of the bar


def _ramp_positions(image: np.ndarray, tolerance: float = 10) -> np.ndarray:
    """Position on the error ramp (0..1) of each pixel of the ramp's colour (others are left out)."""
    t = np.linspace(0, 1, 256)
    ramp = np.stack([np.interp(t, [k for k, _ in ERROR_RAMP], [c[a] for _, c in ERROR_RAMP]) for a in range(3)], 1)
    distance, index = cKDTree(ramp * 255).query(image[..., :3].reshape(-1, 3).astype(float))
    return t[index[distance <= tolerance]]


def test_headless_chromium_draws_both_clouds_and_the_error_colours(tmp_path, intensity_files, model_dir):
    """The page rendered by a real browser (WebGL through SwiftShader): in the side-by-side layout the original's
    colour fills the left pane and the decoded one's the right pane; coloured by error, the points span the ramp
    and the colour bar shows it; coloured by intensity, the points are greys from dark to bright."""
    _require_chromium()
    from matplotlib.image import imread

    ply, msq = intensity_files
    page = tmp_path / "view.html"
    write_view(ViewInput("tiny", msq, original=load_cloud(ply), model=model_dir), page, 4000)
    clouds = imread(screenshot(page, tmp_path / "clouds.png", "color=cloud&layout=side&size=3", size=(1000, 600)))
    clouds = (clouds * 255).round().astype(np.uint8) if clouds.dtype != np.uint8 else clouds
    stage = clouds[: 600 - 80, : 1000 - PANEL_PX]  # above the legend
    half = stage.shape[1] // 2
    left, right = stage[:, :half], stage[:, half:]
    assert _near(left, ORIGINAL_RGB).sum() > 800 and _near(right, DECODED_RGB).sum() > 800  # (random weights: clumps)
    assert _near(left, DECODED_RGB).sum() < 50 and _near(right, ORIGINAL_RGB).sum() < 50

    errors = imread(screenshot(page, tmp_path / "errors.png", "color=error&size=3", size=(1000, 600)))
    errors = (errors * 255).round().astype(np.uint8) if errors.dtype != np.uint8 else errors
    points_area = errors[30: 600 - 80, : 1000 - PANEL_PX]  # below the point counts, above the colour bar
    on_ramp = _ramp_positions(points_area)
    drawn = (~_near(points_area, BACKGROUND_RGB, 2)).sum()
    assert len(on_ramp) > 0.9 * drawn > 2000  # the points are drawn in the ramp's colours ...
    # ... from small errors to saturated ones
    assert min((on_ramp < 0.25).sum(), ((on_ramp > 0.4) & (on_ramp < 0.6)).sum(), (on_ramp > 0.97).sum()) > 100
    assert _near(points_area, ORIGINAL_RGB, 12).sum() < 50
    bar = _ramp_positions(errors[600 - 80:, : 1000 - PANEL_PX], tolerance=4)  # the colour bar: the whole ramp
    assert np.histogram(bar, bins=10, range=(0, 1))[0].min() >= 14 * 30

    shades = imread(screenshot(page, tmp_path / "intensity.png", "color=intensity&size=3", size=(1000, 600)))
    shades = (shades * 255).round().astype(np.uint8) if shades.dtype != np.uint8 else shades
    pixels = shades[30: 600 - 80, : 1000 - PANEL_PX, :3].reshape(-1, 3).astype(int)  # as for the errors
    pixels = pixels[~_near(pixels, BACKGROUND_RGB, 2)]
    grey = pixels.max(axis=1) - pixels.min(axis=1) <= 3  # RAMPS.intensity of viewer.js: dark grey to white
    assert grey.sum() > 0.9 * len(pixels) > 2000
    assert min((pixels[grey, 0] < 64).sum(), (pixels[grey, 0] > 128).sum()) > 1000  # low and high intensities


def test_a_file_beyond_the_default_tile_limit_warns_at_compress_and_views_with_the_flag(tmp_path, map_points,
                                                                                          model_dir, run_cli,
                                                                                          monkeypatch):
    """A network tile whose native count is above the per-tile guard (a volume filled with points at e3: 13M
    points, over 2^23) is named by a warning at compress, with the --max-tile-points that decodes it, and `view`
    takes that flag as `decompress` does (it had none, so such a file could not be viewed). The guard is lowered
    here to the tiny model's native count minus one."""
    import mapsqueeze.codec.tilejobs as tilejobs_module

    data = mapsqueeze.compress(map_points, model=model_dir, fallback=False)
    natives = [len(tile.embedding) for tile in mapsqueeze.tiles(data)]
    factor = int(np.prod(load_model(model_dir).config.upsampling_factors))
    limit = max(natives) * factor - 1
    monkeypatch.setattr(tilejobs_module, "DEFAULT_MAX_TILE_POINTS", limit)
    np.save(tmp_path / "map.npy", map_points)
    code, out, err = run_cli("compress", str(tmp_path / "map.npy"), "-o", str(tmp_path / "map.msq"), "--model",
                             str(model_dir), "--no-fallback", "--post-filter", "off")
    assert code == 0 and err.count("\n") == 1, err
    assert err.startswith("warning: 1 tile decodes to more than the") and \
        f"--max-tile-points {limit + 1}" in err
    code, out, err = run_cli("view", str(tmp_path / "map.msq"), "-o", str(tmp_path / "v.html"), "--model",
                             str(model_dir), "--max-tile-points", str(limit))
    assert code == 2 and "more than the limit of" in err and not (tmp_path / "v.html").exists()
    code, out, err = run_cli("view", str(tmp_path / "map.msq"), "-o", str(tmp_path / "v.html"), "--model",
                             str(model_dir), "--max-tile-points", str(limit + 1))
    assert code == 0 and (tmp_path / "v.html").exists(), err


def test_a_tile_over_the_limit_by_its_input_count_warns_too(model_dir, monkeypatch):
    """decompress also refuses a tile whose input count (what --points splits by) is over the guard, whatever its
    coding: a raw tile of 60 points with the guard at 59 is named with the flag that decodes it."""
    import mapsqueeze.codec.tilejobs as tilejobs_module
    from mapsqueeze.errors import DecodeLimitError, TileLimitWarning

    sparse = np.random.default_rng(5).uniform(0, [7, 7, 3], (60, 3))
    monkeypatch.setattr(tilejobs_module, "DEFAULT_MAX_TILE_POINTS", 59)
    with pytest.warns(TileLimitWarning, match=r"1 tile decodes to more than the 59 points .* \(tile \(0, 0, 0\): 60\); "
                                              r"decompress or view with --max-tile-points 60"):
        data = mapsqueeze.compress(sparse, model=model_dir)
    assert [tile.coding for tile in mapsqueeze.tiles(data)] == ["raw"]
    with pytest.raises(DecodeLimitError):
        mapsqueeze.decompress(data, model=model_dir, max_tile_points=59)
    assert len(mapsqueeze.decompress(data, model=model_dir, max_tile_points=60)) == 60
