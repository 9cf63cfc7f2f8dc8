"""`ago experiments report` on a made-up experiments folder (no training): the tables it prints from the runs'
views.json (seed means, missing runs, the paper's table under ours), results.json keeping every seed, the charts
drawn through ago_runtime.pictures.charts, and the renders' labels mapped into the data's class table (its free
id, not a fixed 17). tests/test_experiments.py runs the whole driver on the tiny profile."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from ago_runtime.atomic import write_json  # noqa: E402
from ago_runtime.classes import OCC3D_NUSCENES, OCC3D_WAYMO  # noqa: E402
from ago_train.experiments.driver import EXPERIMENTS, runs_for  # noqa: E402
from ago_train.experiments.plan import ExperimentProfile  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
VIEWS = ("cw", "cw-min-entropy", "ow-none", "ow-max-conf", "ow-min-entropy", "ow-adapted", "ow-closed", "ow-pretrain")
SKIPPED = "cw/ago-no-noise"   # two runs of Tab. 5 (-no-noise, -no-noise-no-occ; both seeds) are left out


def value(name: str) -> float:
    """Every number of run `name`'s views: its position in the sorted run list (so seed means are known)."""
    return float(RUNS.index(name))


RUNS = sorted({s.name for e in EXPERIMENTS for s in runs_for(e, ExperimentProfile.preset("tiny"))})


def view(v: float) -> dict:
    return {"mIoU": v, "mIoU_star": v, "geometry_IoU": v, "subsets": {"known": v, "unknown": v},
            "metric": {"iou": {}}}


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("report") / "exp"
    for name in RUNS:
        if name.startswith(SKIPPED):
            continue
        d = {"views": {k: view(value(name)) for k in VIEWS}, "eval_s": 2.0}
        if name == "ow/ago":
            d["stats"] = {"classes": ["car", "tree", "road"], "known": ["car"], "entropy_main": [0.5, 1.0, 1.5],
                          "entropy_adapted": [1.0, 0.5, 0.2], "cos_main": np.eye(3).tolist(),
                          "cos_adapted": (np.eye(3) / 2).tolist()}
        write_json(out / "runs" / name / "views.json", d)
        write_json(out / "runs" / name / "done.json", {"steps": 3, "wall_s_last_session": 10.0})
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), AGO_NO_PROGRESS="1")
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", "experiments", "report", "--profile", "tiny",
                        "--out", str(out)], capture_output=True, text=True, env=env, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return out


def mean(*names: str) -> str:
    vals = [value(n) for n in names]
    return f"{np.mean(vals):.2f} ({', '.join(f'{v:.2f}' for v in vals)})"


def test_tables_print_seed_means_and_say_what_is_missing(report):
    md = (report / "results.md").read_text()
    # Tab. 5: each row the mean of the run's two seeds, 'mean (a, b)'; the left-out run's row empty and named
    full = mean("cw/ago", "cw/ago-seed1")
    assert f"| yes | yes | {full} | {full} |" in md
    assert "| no | no | – | – |" in md and "| no | yes | – | – |" in md
    assert f"| yes | no | {mean('cw/ago-no-occ', 'cw/ago-no-occ-seed1')} |" in md
    assert (f"Not run yet: {SKIPPED}-no-occ, {SKIPPED}-no-occ-seed1, {SKIPPED}, {SKIPPED}-seed1.") in md
    # Tab. 3: the AGO paradigm's closed-world and zero-shot columns come from its own runs
    ow = mean("ow/ago", "ow/ago-seed1")
    assert f"| AGO (adaptive grounding) | {mean('cw/ago', 'cw/ago-seed1')} | " in md and f" | {ow} | {ow} | {ow} |" in md
    # the paper's table under ours
    assert "Paper, " in md.split("## Tab. 5")[1].split("\n## ")[0]
    # results.json keeps each seed's value beside the mean
    res = json.loads((report / "results.json").read_text())
    row = [r for r in res["tables"]["tab5"]["rows"] if r["noise_prompts"] and r["L_occ"]][0]
    assert row["per_seed"]["mIoU"] == [value("cw/ago"), value("cw/ago-seed1")]
    assert res["steps"]["cw/ago"] == 3 and res["times"]["cw/ago"] == {"train_s": 10.0, "eval_s": 2.0}


def test_charts_are_drawn(report):
    import cv2

    for png in ("entropy_per_class.png", "modality_gap.png"):
        img = cv2.imread(str(report / "figures" / png))
        assert img is not None and img.shape[0] > 100 and len(np.unique(img.reshape(-1, 3), axis=0)) > 10
    assert not (report / "figures" / "voxel_renders.png").exists()   # no kept predictions: no renders


def test_render_labels_take_the_free_id_from_the_class_table():
    from ago_train.experiments.figures import table_labels

    names = ["vehicle", "road", "no_such_class"]
    pred = np.array([0, 1, 2, 3], np.uint8)                     # K = 3 is free
    assert table_labels(pred, names, OCC3D_WAYMO).tolist() == [OCC3D_WAYMO.id_of("vehicle"), OCC3D_WAYMO.id_of("road"),
                                                               255, 23]
    # pseudo-label files store free as 17 whatever K is
    assert table_labels(np.array([1, 17], np.uint8), names, OCC3D_WAYMO, free=17).tolist() == [13, 23]
    cw = list(OCC3D_NUSCENES.names)
    assert table_labels(np.arange(18, dtype=np.uint8), cw, OCC3D_NUSCENES).tolist() == list(range(18))
