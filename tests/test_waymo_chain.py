"""Issue 38: the whole chain on a tiny synthetic Occ3D-Waymo town, in the Occ3D-Waymo layout:
`ago synth --rig waymo` -> `ago pseudo-labels` (simulated segmenter, the closed Waymo label space) ->
`ago train` (tiny preset) -> `ago eval` (Waymo classes, free = id 23 scored as the last label) ->
`ago export` -> `ago infer` on the layout's frames -> `ago metric` against the Waymo GT files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from ago_runtime.classes import OCC3D_WAYMO  # noqa: E402
from ago_runtime.formats.datasets import open_dataset  # noqa: E402
from ago_train.synth.rigs import WAYMO_CAMERAS  # noqa: E402
from test_bad_inputs import assert_one_error_line, ok, run_ago, run_chain  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_waymo_chain")  # one worker builds the module fixtures (--dist loadgroup)

PROMPTS = "waymo/cw_waymo"          # the shipped closed Occ3D-Waymo label space (15 classes, Tab. G)
WAYMO_NAMES = list(OCC3D_WAYMO.names)


@pytest.fixture(scope="module")
def chain(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("waymo_chain")
    ok(run_ago(["synth", "--rig", "waymo", "--out", "w", "--scenes", "2", "--frames", "3", "--image-size", "192x128",
            "--grid", "40x40x4", "--seed", "5"], d))
    run_chain(d, "w", PROMPTS, gt="w")
    return d


def test_synth_writes_lidar_and_extras_and_pseudo_labels_use_them(chain):
    w = chain / "w"
    assert sorted(p.name for p in (w / "kitti_format" / "training").iterdir()) == \
        [f"image_{k}" for k in range(5)] + ["velodyne"]
    assert sorted(p.name for p in (w / "synthetic" / "semantic").iterdir()) == sorted(WAYMO_CAMERAS)
    meta = json.loads((chain / "pl" / "meta.json").read_text())
    assert meta["segmenter"]["name"] == "simulated" and meta["label_space"]["classes"] == WAYMO_NAMES
    ds = open_dataset(w, load_images=False, load_extras=False)
    for i in ds.split("train"):
        path = chain / "pl" / ds.scene_of(i) / ds.sample_tokens[i] / "labels.npz"
        with np.load(path) as z:
            sem = z["semantics"]
        assert sem.shape == (20, 20, 4)
        values = set(np.unique(sem).tolist())
        assert values <= set(range(15)) | {17, 255}   # 15 Waymo classes; the pseudo format's free 17, unknown 255
        assert 17 in values and len(values - {17, 255}) >= 3  # free space and several classes were lifted
        # the lifted classes sit where the Waymo GT has those classes (a coarse check of the mapping)
        gt = ds[i].gt.semantics[::2, ::2, :]
        lab = sem < 15
        assert (gt[lab] != OCC3D_WAYMO.free_id).mean() > 0.6


def test_training_and_bundle_take_the_waymo_rig(chain):
    from ago_runtime.predict.bundle import Bundle

    b = Bundle.load(chain / "bundle")
    assert b.rig.names == list(WAYMO_CAMERAS)
    heights = [c.height for c in b.rig]
    assert len(set(heights)) == 2 and heights[3] == heights[4] < heights[0] == heights[1] == heights[2]
    assert list(b.load_bank().class_names) == WAYMO_NAMES


def test_eval_scores_in_the_waymo_table_with_free_23_as_the_last_label(chain):
    m = json.loads((chain / "ev" / "metrics.json").read_text())
    assert m["label_space"] == "cw_waymo" and m["frames"] == 3
    assert m["metric"]["class_names"] == WAYMO_NAMES + ["free"] and m["metric"]["free_index"] == 15
    ds = open_dataset(chain / "w", load_images=False, load_extras=False)
    free = sum(int(((f.gt.semantics == 23) & f.gt.mask_camera.astype(bool)).sum())
               for f in (ds[i] for i in ds.split("val")))
    vehicle = sum(int(((f.gt.semantics == 1) & f.gt.mask_camera.astype(bool)).sum())
                  for f in (ds[i] for i in ds.split("val")))
    assert free > 0 and m["metric"]["counts"]["free"]["gt"] == free          # GT id 23 counted as "free"
    assert m["metric"]["counts"]["vehicle"]["gt"] == vehicle                 # GT id 1 as "vehicle"


def test_infer_and_metric_on_the_waymo_layout(chain):
    pred = sorted(p.name for p in (chain / "pred").glob("*.npz"))
    assert pred == [f"{p}{s:03d}{f:03d}.npz" for p, s in ((0, 0), (1, 0)) for f in range(3)]
    with np.load(chain / "pred" / "1000001.npz") as z:
        # the labels in the bank's classes (the Waymo table's 15, then free), what `ago metric --prompts` reads
        assert [str(c) for c in z["bank_class_names"]] == WAYMO_NAMES + ["free"]
        assert z["bank_semantics"].shape == (20, 20, 4) and z["bank_semantics"].max() <= 15
    m = json.loads((chain / "m.json").read_text())
    assert m["class_names"] == WAYMO_NAMES + ["free"] and m["frames"] == 6 and m["skipped_frames"] == []
    assert m["counts"]["free"]["gt"] > 0


def test_the_chain_refuses_a_label_space_of_another_table(chain):
    assert_one_error_line(run_ago(["pseudo-labels", "--data", "w", "--prompts", "cw", "--out", "bad"], chain), "--prompts",
              "occ3d_waymo")
    assert not (chain / "bad").exists()
    assert_one_error_line(run_ago(["metric", "--pred", "pred", "--gt", "w"], chain), "occ3d_waymo", "--prompts")
    assert_one_error_line(run_ago(["eval", "--ckpt", "run/last.pt", "--data", "w", "--prompts", "cw"], chain), "occ3d_waymo")


def test_seen_gt_mixes_the_waymo_ground_truth_in(chain):
    """`ago seen-gt` on the Occ3D-Waymo layout: the seen classes come from its `_04.npz` files (Waymo ids)."""
    text = (chain.parent / "cw_waymo_seen.txt")
    from ago_runtime.vocab.prompts import resolve_prompt_file

    src = resolve_prompt_file(PROMPTS).read_text(encoding="utf-8")
    lines = [ln for ln in src.splitlines() if not ln.startswith("@known")]
    at = max(i for i, ln in enumerate(lines) if ln.startswith("@")) + 1
    text.write_text("\n".join(lines[:at] + ["@known: vehicle, road"] + lines[at:]) + "\n", encoding="utf-8")
    ok(run_ago(["seen-gt", "--data", "w", "--pseudo", "pl", "--prompts", text, "--out", "pl_seen"], chain))
    meta = json.loads((chain / "pl_seen" / "meta.json").read_text())
    assert sorted(meta["seen_gt"]["seen"]) == ["road", "vehicle"]
    assert len(list((chain / "pl_seen").rglob("labels.npz"))) == len(list((chain / "pl").rglob("labels.npz"))) > 0
    changed = 0
    for f in (chain / "pl").rglob("labels.npz"):
        with np.load(f) as a, np.load(chain / "pl_seen" / f.relative_to(chain / "pl")) as b:
            changed += int((a["semantics"] != b["semantics"]).sum())
    assert changed > 0   # the seen classes' voxels were taken from the GT files


def test_defaults_follow_the_data(chain):
    """Issue 51 (5): with no --prompts, pseudo-labels take the data's table's closed prompt file, and training takes
    the prompt file the pseudo-labels were made with; no 'no such file here' note for a name nobody typed."""
    r = run_ago(["pseudo-labels", "--data", "w", "--out", "pl_default", "--grid", "20x20x4", "--limit", "1"], chain)
    ok(r)
    assert "waymo/cw_waymo.txt (the closed prompt file of the data's label table)" in r.stdout
    assert "no such file here" not in r.stdout + r.stderr
    meta = json.loads((chain / "pl_default" / "meta.json").read_text())
    assert meta["label_space"]["classes"] == WAYMO_NAMES
    r = run_ago(["train", "--config", "tiny", "--data", "w", "--pseudo", "pl_default", "--out", "run_default",
                 "--print-config"], chain)
    ok(r)
    assert json.loads(r.stdout[r.stdout.index("{"):])["prompts"].endswith("cw_waymo.txt")
    assert "pseudo-labels in pl_default were made with" in r.stdout
    # a prompt file named on the command line still wins (and a wrong one is refused as before)
    r = run_ago(["train", "--config", "tiny", "--data", "w", "--pseudo", "pl_default", "--out", "run_default",
                 "--prompts", "cw", "--print-config"], chain)
    ok(r)
    assert json.loads(r.stdout[r.stdout.index("{"):])["prompts"] == "cw"
