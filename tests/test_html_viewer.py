"""The 3-D page (`ago show --html`, `ago demo|infer|retrieve --html`; ago_runtime/pictures/html_viewer.py), opened in
a real browser: headless Chromium (software WebGL) loads the file, the page's API (window.agoViewer) writes what it
drew into a DOM element read with --dump-dom, and screenshots are checked pixel by pixel (class colours are unlit:
a cube's top face is exactly its class colour). Without a browser those tests are skipped with a one-line reason.
"""

from __future__ import annotations

import base64
import html
import json
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.classes import FREE, OCC3D_CLASSES, OCC3D_COLORS
from ago_runtime.errors import AgoNote
from ago_runtime.pictures import html_viewer
from ago_runtime.pictures.html_viewer import view_from_arrays, viewer_html, write_viewer

REPO = Path(__file__).resolve().parents[1]
CAR, BARRIER, ROAD, VEG = (OCC3D_CLASSES.index(n) for n in ("car", "barrier", "driveable_surface", "vegetation"))
WINDOW = (1200, 800)


def _browser() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _chromium(url: str, *args: str) -> str:
    exe = _browser()
    if exe is None:
        pytest.skip("no Chromium here (Debian: apt-get install chromium; .ci/run installs it)")
    cmd = [exe, "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
           "--disable-gpu-sandbox", "--force-device-scale-factor=1", f"--window-size={WINDOW[0]},{WINDOW[1]}",
           "--virtual-time-budget=10000", "--hide-scrollbars", *args, url]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def open_page(path: Path, fragment: str = "") -> tuple[dict, str, np.ndarray]:
    """(the JSON the page wrote into #ago-result, the page's DOM, a screenshot RGB) after one Chromium run loaded
    `path#fragment`."""
    shot = path.parent / f"{path.stem}_{len(list(path.parent.glob('*.shot.png')))}.shot.png"
    url = path.resolve().as_uri() + (f"#{fragment}" if fragment else "")
    dom = _chromium(url, "--dump-dom", f"--screenshot={shot}")
    m = re.search(r'<pre id="ago-result">([^<]*)</pre>', dom)
    assert m and m.group(1), "the page wrote no result (its script failed?)"
    result = json.loads(html.unescape(m.group(1)))
    if not result["webgl"]:
        pytest.skip("Chromium gives no WebGL here (software rendering, SwiftShader, missing)")
    return result, dom, cv2.imread(str(shot))[:, :, ::-1]


def _has_colour(rgb: np.ndarray, rect, colour) -> int:
    x, y, w, h = rect
    crop = rgb[y + 2:y + h - 2, x + 2:x + w - 2].astype(np.int32)
    return int(np.all(crop == np.asarray(colour, np.int32), axis=-1).sum())


def _scene(shape=(40, 40, 8)) -> np.ndarray:
    """A small labelled grid: a road slab, a car, a barrier wall, a tree."""
    sem = np.full(shape, FREE, np.uint8)
    sem[:, 10:30, 1] = ROAD
    sem[24:30, 16:20, 2:4] = CAR
    sem[5:35, 32, 2:4] = BARRIER
    sem[8:11, 5:8, 2:7] = VEG
    return sem


def _file_counts(sem: np.ndarray) -> dict:
    values, n = np.unique(sem[sem != FREE], return_counts=True)
    return {OCC3D_CLASSES[v]: int(c) for v, c in zip(values, n)}


def _decode_indices(view: dict) -> np.ndarray:
    raw = np.frombuffer(base64.b64decode(view["index"]), np.uint8)
    if view["index_kind"] == "uint32":
        return raw.view("<u4")
    return np.flatnonzero(np.unpackbits(raw, bitorder="little"))


def _page_data(text: str) -> dict:
    m = re.search(r'<script type="application/json" id="ago-data">(.*?)</script>', text, re.S)
    return json.loads(m.group(1))


# ------------------------------------------------------------------------------------ the file (no browser)
def test_page_is_self_contained_and_holds_exactly_the_occupied_voxels():
    sem = _scene()
    ent = np.random.default_rng(0).random(sem.shape).astype(np.float32) * 2
    text = viewer_html([view_from_arrays({"semantics": sem, "entropy": ent}, "t", "prediction")], title="t")
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", text, re.I)   # nothing fetched: no CDN
    assert "<link" not in text and "import(" not in text.split('id="ago-data"')[0]
    assert "OrbitControls" in text or "_interceptControlUp" in text                   # three.js is inlined
    v = _page_data(text)["views"][0]
    idx = _decode_indices(v)
    assert np.array_equal(idx, np.flatnonzero(sem.ravel() != FREE))
    labels = np.frombuffer(base64.b64decode(v["labels"]), np.uint8)
    assert np.array_equal(labels, sem.ravel()[idx])
    s = v["scalars"][0]
    q = np.frombuffer(base64.b64decode(s["data"]), "<u2")
    back = s["lo"] + q * (s["hi"] - s["lo"]) / 65535
    assert np.abs(back - ent.ravel()[idx]).max() < 1e-4
    assert {c["name"]: c["color"] for c in v["classes"]}["car"] == OCC3D_COLORS[CAR].tolist()


def test_bank_classes_get_the_pngs_colours_and_names_cannot_break_the_page():
    from ago_runtime.pictures.render import palette_for

    names = ["fire hydrant", "</script><script>alert(1)</script>", "car"]
    sem = np.full((20, 20, 4), 3, np.uint8)
    sem[2:5, 2:5, 1] = [0, 1, 2]
    arrays = {"semantics": sem, "class_names": np.array(names + ["free"]), "free_index": np.array(3)}
    text = viewer_html([view_from_arrays(arrays, "b", "prediction")], title="<b> & </title>")
    data = _page_data(text)                         # the data block ends where it should and parses
    assert [c["name"] for c in data["views"][0]["classes"]] == names
    assert [c["color"] for c in data["views"][0]["classes"]] == palette_for(names).tolist()
    assert text.count("</script>") == 3             # the data, three.js and the viewer's script
    assert "<title>&lt;b&gt; &amp; &lt;/title&gt;</title>" in text


def test_a_full_frame_with_six_images_stays_under_3_mb(tmp_path):
    """200 x 200 x 16 with as many occupied voxels as the demo's prediction (53k), entropy and the unexplained
    score, and six 1600 x 900 camera images (downscaled to 800 px wide JPEGs)."""
    rng = np.random.default_rng(1)
    sem = np.full((200, 200, 16), FREE, np.uint8)
    sem[:, :, 1] = ROAD
    sem[rng.random(sem.shape) < 0.03] = CAR
    demo = REPO / "ago_runtime" / "assets" / "demo_frame"
    images = {p.stem: cv2.resize(cv2.imread(str(p))[:, :, ::-1], (1600, 900)) for p in sorted(demo.glob("CAM_*.jpg"))}
    assert len(images) == 6
    arrays = {"semantics": sem, "entropy": rng.random(sem.shape, np.float32),
              "unexplained": rng.random(sem.shape, np.float32), "unexplained_threshold": np.float32(0.5)}
    out = write_viewer(tmp_path / "f.html", [view_from_arrays(arrays, "f", "prediction")], images, "f")
    size = out.stat().st_size
    assert size < 3_000_000, size
    data = _page_data(out.read_text())
    widths = [cv2.imdecode(np.frombuffer(base64.b64decode(im["jpeg"]), np.uint8), cv2.IMREAD_COLOR).shape[1]
              for im in data["images"]]
    assert widths == [800] * 6
    assert [im["name"] for im in data["images"]][:3] == ["CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"]


def test_too_many_voxels_drops_the_farthest_with_a_note(monkeypatch):
    monkeypatch.setattr(html_viewer, "MAX_DRAWN_VOXELS", 300)
    sem = _scene()
    view = view_from_arrays({"semantics": sem}, "big.npz", "prediction")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = _page_data(viewer_html([view], source="big.npz"))
    notes = [str(w.message) for w in caught if issubclass(w.category, AgoNote)]
    assert len(notes) == 1 and "dropped the" in notes[0] and "farther" in notes[0], notes
    assert data["notes"] == notes and data["views"][0]["count"] == 300
    kept = _decode_indices(data["views"][0])
    X, Y, Z = sem.shape
    grid = view.grid
    cx, cy, _ = grid.axis_centres()
    occupied = np.flatnonzero(sem.ravel() != FREE)
    dist = lambda f: np.hypot(cx[f // (Y * Z)], cy[(f // Z) % Y])   # noqa: E731
    dropped = np.setdiff1d(occupied, kept)
    assert dropped.size == occupied.size - 300 and dist(kept).max() <= dist(dropped).min()


def _run_ago(args, cwd):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), AGO_NO_PROGRESS="1")
    return subprocess.run([sys.executable, "-m", "ago_runtime.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=300)


def test_show_html_bad_inputs_are_one_error_line(tmp_path):
    np.savez(tmp_path / "notpred.npz", similarity=np.zeros((4, 4, 2), np.float32))
    np.savez(tmp_path / "nocolours.npz", semantics=_scene(), class_table=np.array("my_table"),
             class_names=np.array(["a", "b", "free"]))
    np.savez(tmp_path / "ok.npz", semantics=_scene())
    (tmp_path / "gts" / "scene-1" / "other").mkdir(parents=True)
    np.savez(tmp_path / "gts" / "scene-1" / "other" / "labels.npz", semantics=_scene())
    for args, needle in (([tmp_path / "notpred.npz", "--html", tmp_path / "a.html"], "no 'semantics'"),
                         ([tmp_path / "nocolours.npz", "--html", tmp_path / "b.html"], "class_colors"),
                         ([tmp_path / "ok.npz", "--html", tmp_path / "c.png"], "--html"),
                         ([tmp_path / "ok.npz", "--html", tmp_path / "d.html", "--gt", tmp_path / "gts"],
                          "no ground truth for sample 'ok'")):
        r = _run_ago(["show", *args], tmp_path)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], r.stderr
        assert not list(tmp_path.glob("*.html"))   # nothing half-written
    r = _run_ago(["show", tmp_path / "ok.npz", "--html", tmp_path / "ok.html"], tmp_path)
    assert r.returncode == 0 and (tmp_path / "ok.html").is_file() and not (tmp_path / "ago_show.png").exists()
    (tmp_path / "gts" / "scene-1" / "other").rename(tmp_path / "gts" / "scene-1" / "ok")   # found by its token
    r = _run_ago(["show", tmp_path / "ok.npz", "--gt", tmp_path / "gts", "--html", tmp_path / "gt.html"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert [v["title"] for v in _page_data((tmp_path / "gt.html").read_text())["views"]] == ["prediction",
                                                                                            "ground truth"]


# ------------------------------------------------------------------------------------ in the browser
def test_browser_draws_the_files_voxels_per_class_and_hover_names_them(tmp_path):
    """Both encodings of which voxels are drawn: a bitmask (dense) and uint32 indices (a sparse 200 x 200 x 16)."""
    sem = _scene()
    sparse = np.full((200, 200, 16), FREE, np.uint8)
    sparse[[3, 50, 199], [7, 100, 0], [0, 5, 15]] = [CAR, VEG, CAR]
    views = [view_from_arrays({"semantics": sem}, "p", "prediction"),
             view_from_arrays({"semantics": sparse}, "s", "sparse")]
    page = write_viewer(tmp_path / "p.html", views, title="p")
    assert [v["index_kind"] for v in _page_data(page.read_text())["views"]] == ["bitmask", "uint32"]
    result, _, _ = open_page(page, "pick=0.5,0.5")
    assert result["counts"] == {"prediction": _file_counts(sem), "sparse": {"car": 2, "vegetation": 1}}
    assert result["empty"] == [] and result["pick"] is not None
    first_line = result["pick"].splitlines()[0]
    assert first_line.split()[0] in _file_counts(sem)   # the ray from the view's centre meets a drawn voxel


def test_browser_hiding_a_class_removes_it_and_its_colour(tmp_path):
    sem = _scene()
    page = write_viewer(tmp_path / "p.html", [view_from_arrays({"semantics": sem}, "p", "prediction")], title="p")
    result, _, hidden = open_page(page, "click=car")   # a click on the legend's entry
    expect = _file_counts(sem)
    del expect["car"]
    assert result["counts"] == {"prediction": expect} and result["hidden"] == ["car"]
    shown_result, _, shown = open_page(page)
    rect = result["rects"][0]
    assert shown_result["rects"][0] == rect and shown_result["hidden"] == []
    both, _, _ = open_page(page, "hide=car&click=car")   # a second click shows it again
    assert both["counts"] == {"prediction": _file_counts(sem)}
    car = OCC3D_COLORS[CAR]
    assert _has_colour(shown, rect, car) > 50                       # top faces in the exact class colour
    assert _has_colour(hidden, rect, car) == 0
    assert _has_colour(hidden, rect, OCC3D_COLORS[ROAD]) > 1000     # the rest is still drawn


def test_browser_all_free_prediction_says_so(tmp_path):
    sem = np.full((40, 40, 8), FREE, np.uint8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        page = write_viewer(tmp_path / "f.html", [view_from_arrays({"semantics": sem}, "f", "prediction")], title="f")
    assert any("every voxel is free" in str(w.message) for w in caught)
    result, dom, _ = open_page(page)
    assert result["empty"] == ["prediction"] and result["counts"] == {"prediction": {}}
    assert "all 12,800 voxels are free: nothing to draw" in dom


def test_browser_gt_beside_the_prediction_and_heat_threshold(tmp_path):
    """--gt: two views, each drawing its own voxels; the unexplained score as heat: the slider's threshold leaves
    only the voxels at or above it."""
    pred = _scene()
    gt = _scene()
    gt[24:30, 16:20, 2:4] = FREE                       # no car in the ground truth
    score = np.zeros(pred.shape, np.float32)
    score[5:35, 32, 2:4] = 0.9                         # the barrier wall is "unexplained"
    np.savez(tmp_path / "pred.npz", semantics=pred, unexplained=score, unexplained_threshold=np.float32(0.5))
    np.savez(tmp_path / "gt.npz", semantics=gt)
    r = _run_ago(["show", tmp_path / "pred.npz", "--gt", tmp_path / "gt.npz", "--html", tmp_path / "v.html"], tmp_path)
    assert r.returncode == 0, r.stderr
    result, _, _ = open_page(tmp_path / "v.html")
    assert result["counts"] == {"prediction": _file_counts(pred), "ground truth": _file_counts(gt)}
    heat, _, _ = open_page(tmp_path / "v.html", "mode=unexplained")
    assert heat["mode"] == "unexplained"
    assert heat["counts"]["prediction"] == {"barrier": int((pred == BARRIER).sum())}
    assert heat["counts"]["ground truth"] == _file_counts(gt)   # no score in the GT file: its classes


def test_demo_html_is_written_beside_its_png_and_draws_the_prediction(tmp_path):
    r = _run_ago(["demo", "--out", tmp_path / "d", "--html"], tmp_path)
    assert r.returncode == 0, r.stderr
    d = tmp_path / "d"
    assert (d / "demo_frame.png").is_file() and (d / "demo_frame.html").is_file()
    assert (d / "demo_frame.html").stat().st_size < 3_000_000
    with np.load(d / "demo_frame.npz") as z:
        sem, names = z["semantics"], [str(n) for n in z["class_names"]]
    result, dom, _ = open_page(d / "demo_frame.html")
    values, n = np.unique(sem[sem != names.index("free")], return_counts=True)
    assert result["counts"] == {"prediction": {names[v]: int(c) for v, c in zip(values, n)}}
    assert dom.count("<figcaption>CAM_") == 6


def test_retrieve_html_opens_on_the_similarity_with_its_slider(tmp_path):
    demo = REPO / "ago_runtime" / "assets" / "demo_frame"
    r = _run_ago(["retrieve", "--phrase", "traffic cone", "--images", demo, "--out", tmp_path / "r", "--html"],
                 tmp_path)
    assert r.returncode == 0, r.stderr
    page = tmp_path / "r" / "demo_frame_traffic_cone.html"
    assert page.is_file() and (tmp_path / "r" / "demo_frame_traffic_cone.png").is_file()
    data = _page_data(page.read_text())
    assert data["mode"] == "similarity" and len(data["images"]) == 6
    sim = {s["name"]: s for s in data["views"][0]["scalars"]}["similarity"]
    with np.load(tmp_path / "r" / "demo_frame_traffic_cone.npz") as z:
        occupied_sim = z["similarity"][z["occupied"].astype(bool)]
    assert np.isclose(sim["lo"], occupied_sim.min()) and np.isclose(sim["hi"], occupied_sim.max())
    assert np.isclose(sim["threshold"], np.quantile(occupied_sim, 0.9), atol=1e-6)
