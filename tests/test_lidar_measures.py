"""`ago metric --lidar` measures that a constant cannot win (issue 46): object ray IoU, ground / non-ground
geometry ray IoU, judged-voxel F1, beside the no-image baselines and a training-frame prior.

On a synthetic town with ground truth (`ago synth`): the GT as the prediction tops every baseline on every
primary measure, the training-frame prior (made from the GT of other frames) scores below the GT, and the
GT with its object voxels moved 2 m scores lower at 1 m than the GT."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.classes import FREE, OCC3D_CLASSES
from ago_runtime.formats.nuscenes_boxes import BOX_CLASSES, ground_returns, inside_box, return_classes
from ago_runtime.scoring.lidar_agreement import (PRIMARY, TrainingPrior, baseline_volumes, frame_truth,
                                                 score_frame_counts, score_with_baselines, voxel_centres)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_bad_inputs import assert_one_error_line, run_ago  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_lidar_measures")  # one worker builds the module fixtures (--dist loadgroup)

OBJECT_IDS = [OCC3D_CLASSES.index(c) for c in BOX_CLASSES]
TRAIN_FRAMES = 2     # the first two keyframes make the prior; the other two are scored


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    """A 4-keyframe synthetic town; predictions: its GT and its GT with the object voxels moved 2 m along x
    (5 voxels); a pseudo-label folder holding the GT of the first two keyframes (the prior's training frames)."""
    from ago_runtime.formats.nuscenes import NuScenesDataset

    root = tmp_path_factory.mktemp("town")
    r = run_ago(["synth", "--out", root / "synth", "--scenes", "1", "--frames", "4", "--image-size", "96x54",
                 "--val-fraction", "0"], root)
    assert r.code == 0, r.stderr
    ds = NuScenesDataset(root / "synth", load_images=False, load_extras=False)
    for name in ("gt", "shifted"):
        (root / name).mkdir()
    for i, token in enumerate(ds.sample_tokens):
        gt_file = next((root / "synth" / "gts").glob(f"*/{token}/labels.npz"))
        sem = np.load(gt_file)["semantics"]
        if i < TRAIN_FRAMES:
            d = root / "pseudo" / ds.scene_of(i) / token
            d.mkdir(parents=True)
            shutil.copy(gt_file, d / "labels.npz")
            continue
        np.savez(root / "gt" / f"{token}.npz", semantics=sem)
        objects = np.isin(sem, OBJECT_IDS)
        moved = np.roll(np.where(objects, sem, FREE), 5, axis=0)
        shifted = np.where(moved != FREE, moved, np.where(objects, FREE, sem)).astype(np.uint8)
        assert (shifted != sem).sum() > 100
        np.savez(root / "shifted" / f"{token}.npz", semantics=shifted)
    (root / "pseudo" / "meta.json").write_text(json.dumps({
        "label_space": {"classes": list(OCC3D_CLASSES[:FREE])}, "free_index": FREE,
        "grid": {"shape": [200, 200, 16]}}))
    out = {}
    for name in ("gt", "shifted"):
        r = run_ago(["metric", "--pred", name, "--lidar", "synth", "--allow-missing", "--prior", "pseudo",
                     "--json", f"{name}.json", "--md", f"{name}.md"], root)
        assert r.code == 0, r.stderr
        out[name] = json.loads((root / f"{name}.json").read_text())["lidar"]
    out["root"] = root
    return out


def test_gt_tops_every_baseline_on_every_primary_measure(town):
    s = town["gt"]
    assert s["frames"] == 2 and set(s["baselines"]) == {"all_free", "all_occupied", "slab_0.2", "slab_0.6", "bowl",
                                                         "prior"}
    assert s["prior_frames"] == TRAIN_FRAMES
    gt = s["predictors"]["prediction"]
    assert gt["object_rays"] > 500 and gt["nonground_rays"] > 5000 and gt["ground_rays"] > 5000
    for key in PRIMARY:
        for b in s["baselines"]:
            other = s["predictors"][b][key]
            assert other is None or gt[key] > other, (key, b, gt[key], other)
    assert s["beaten_by"] == {key: [] for key in PRIMARY}
    assert "**Baselines that beat the prediction**: none." in (town["root"] / "gt.md").read_text()
    # the constants: nothing right for all free; all occupied stops every ray in the sensor's own voxel
    assert s["predictors"]["all_free"]["voxel_f1_pct"] == 0 and s["predictors"]["all_free"]["object_ray_iou"] == 0
    assert s["predictors"]["all_occupied"]["voxel_recall_pct"] == 100
    assert s["predictors"]["all_occupied"]["geometry_ray_iou_nonground@1"] == 0
    # the ground slab is good on ground, which is why ground is reported apart
    assert s["predictors"]["slab_0.2"]["geometry_ray_iou_ground@2"] > 80


def test_prior_scores_below_the_gt(town):
    p, gt = town["gt"]["predictors"]["prior"], town["gt"]["predictors"]["prediction"]
    assert 0 < p["object_ray_iou"] < gt["object_ray_iou"]
    assert p["geometry_ray_iou_nonground@1"] < gt["geometry_ray_iou_nonground@1"]
    assert p["voxel_f1_pct"] < gt["voxel_f1_pct"]
    # the prior does know something: it beats the constants on non-ground geometry
    assert p["geometry_ray_iou_nonground@2"] > town["gt"]["predictors"]["bowl"]["geometry_ray_iou_nonground@2"]


def test_boxes_moved_2m_score_lower_at_1m(town):
    gt, sh = town["gt"]["predictors"]["prediction"], town["shifted"]["predictors"]["prediction"]
    assert sh["object_ray_iou@1"] < gt["object_ray_iou@1"] - 10
    assert sh["geometry_ray_iou_nonground@1"] < gt["geometry_ray_iou_nonground@1"]
    assert town["shifted"]["predictors"]["bowl"] == town["gt"]["predictors"]["bowl"]   # baselines do not move


def test_prior_refusals(town, tmp_path):
    root = town["root"]
    r = run_ago(["metric", "--pred", root / "gt", "--gt", root / "synth" / "gts", "--prior", root / "pseudo"], tmp_path)
    assert_one_error_line(r, "--prior", "--lidar")
    r = run_ago(["metric", "--pred", root / "gt", "--lidar", root / "synth", "--allow-missing", "--prior",
                 root / "no_such", "--json", "m.json"], tmp_path)
    assert_one_error_line(r, "no_such")
    assert not (tmp_path / "m.json").exists()
    r = run_ago(["metric", "--pred", root / "gt", "--lidar", root / "synth", "--allow-missing", "--prior",
                 root / "synth"], tmp_path)
    assert_one_error_line(r, "meta.json")
    # a prior made from a scored keyframe is no prior: said
    (tmp_path / "seen").mkdir()
    first = next((root / "pseudo").glob("*/*/labels.npz"))
    np.savez(tmp_path / "seen" / f"{first.parent.name}.npz", semantics=np.load(first)["semantics"])
    r = run_ago(["metric", "--pred", "seen", "--lidar", root / "synth", "--allow-missing", "--prior", root / "pseudo"],
                tmp_path)
    assert r.code == 0 and "note: the training-frame prior saw 1 of the scored keyframes" in r.stdout + r.stderr


# ------------------------------------------------------------------------------------ by hand
RMIN, VS, SHAPE = np.array([-4.0, -4.0, -1.0]), np.array([0.4, 0.4, 0.4]), (30, 20, 10)   # x -4..8 m


def wall_frame():
    """Returns on a wall at x = 2.2 m (voxel layer i = 15: 2.0..2.4 m) seen from a sensor at (0.2, 0.2, 0.2);
    the returns at y < 0 lie in a car box, those at y > 0 below 0.3 m are ground."""
    ys, zs = np.meshgrid(np.linspace(-1.9, 1.9, 12), np.linspace(-0.7, 1.5, 6), indexing="ij")
    pts = np.stack([np.full(ys.size, 2.2), ys.ravel(), zs.ravel()], 1)
    box = np.eye(4)
    box[:3, 3] = [2.2, -1.0, 0.4]
    boxes = [(box, np.array([2.0, 0.4, 2.4]), "car")]     # w (y) 2.0, l (x) 0.4, h 2.4
    return pts, boxes


def layer(i):
    occ = np.zeros(SHAPE, bool)
    occ[i] = True
    return occ


def test_counts_by_hand_on_a_wall():
    pts, boxes = wall_frame()
    cls = return_classes(pts, boxes)
    assert set(cls[pts[:, 1] < 0]) == {"car"} and set(cls[pts[:, 1] > 0]) == {""}
    ground = ground_returns(pts, boxes)
    assert ground.tolist() == ((pts[:, 1] > 0) & (pts[:, 2] < 0.3)).tolist()
    truth = frame_truth("wall", pts, [0.2, 0.2, 0.2], SHAPE, RMIN, VS, BOX_CLASSES, cls, ground)
    car, k, n, n_car = BOX_CLASSES.index("car"), len(BOX_CLASSES), len(pts), int((cls == "car").sum())
    objects = np.full(SHAPE, k)
    objects[15, :10] = car                  # the wall's y < 0 half is a car
    c = score_frame_counts(truth, layer(15), objects, k)
    assert c["rays"] == n and c["part_rays"].tolist() == [int(ground.sum()), n - int(ground.sum())]
    assert c["object_gt"][car] == n_car and c["object_pred"][car] == n_car and (c["object_tp"][:, car] == n_car).all()
    assert (c["part_tp"].sum(axis=1) == n).all()                            # right at every threshold
    assert c["voxel_tp"] == len(truth.occupied_voxels) and c["voxel_fn"] == 0
    # the wall 2.8 m further (layer 22: 4.8..5.2 m): wrong at 1 and 2 m; behind the returns nothing is judged
    c = score_frame_counts(truth, layer(22), None, k)
    assert c["part_tp"][:2].sum() == 0 and 0 < c["part_tp"][2].sum() <= c["part_hit"].sum() < n   # some leave the grid
    assert c["voxel_tp"] == 0 and c["voxel_fn"] == len(truth.occupied_voxels) and c["voxel_fp"] == 0
    assert c["object_pred"].sum() == 0
    # the wall 0.8 m short (layer 13): the rays saw through it -> false positives; 0.8 m along x is more on
    # slanted rays, so right at 2 m but only partly at 1 m
    c = score_frame_counts(truth, layer(13), None, k)
    assert c["voxel_fp"] > 0 and c["voxel_tp"] == 0 and c["part_hit"].sum() == n
    assert 0 < c["part_tp"][0].sum() < n and c["part_tp"][1].sum() == n


def test_ground_returns_are_low_and_outside_boxes():
    pts = np.array([[5.0, 0, 0.1], [5.0, 0, 0.5], [2.2, -1.0, 0.1]])
    box = np.eye(4)
    box[:3, 3] = [2.2, -1.0, 0.4]
    boxes = [(box, np.array([2.0, 0.4, 2.4]), "car")]
    assert ground_returns(pts, boxes).tolist() == [True, False, False]
    assert inside_box(pts, box, [2.0, 0.4, 2.4]).tolist() == [False, False, True]


def test_baselines_spelled_out():
    shape, rmin, vs = (200, 200, 16), (-40.0, -40.0, -1.0), (0.4, 0.4, 0.4)
    b = baseline_volumes(shape, rmin, vs)
    x, y, z = voxel_centres(shape, rmin, vs)
    assert b["slab_0.2"][0, 0].tolist() == [True] * 3 + [False] * 13        # centres -0.8, -0.4, 0.0
    assert b["slab_0.6"][0, 0].sum() == 4                                    # + 0.4
    r = np.hypot(x, y)[..., 0]
    i, j = np.argwhere((r > 6.1) & (r < 29.9))[0]
    assert b["bowl"][i, j].sum() == 4
    i, j = np.argwhere(r < 5.9)[0]
    assert b["bowl"][i, j].sum() == 3
    i, j = np.argwhere(r > 30.1)[0]
    assert b["bowl"][i, j].all()
    assert not b["all_free"].any() and b["all_occupied"].all()


def test_training_prior_mode_ties_to_free():
    p = TrainingPrior(["a", "b"], 17, (3, 1, 1))
    p.add(np.array([0, 1, 255]).reshape(3, 1, 1))
    p.add(np.array([0, 17, 255]).reshape(3, 1, 1))
    assert p.labels().ravel().tolist() == [0, 17, 17]     # mode; tie b/free -> free; never labelled -> free
    p.add(np.array([1, 1, 1]).reshape(3, 1, 1))
    assert p.labels().ravel().tolist() == [0, 1, 1]


def test_score_with_baselines_library_call():
    pts, boxes = wall_frame()
    truth = frame_truth("wall", pts, [0.2, 0.2, 0.2], SHAPE, RMIN, VS, BOX_CLASSES, return_classes(pts, boxes),
                        ground_returns(pts, boxes))
    wall = layer(15)
    prior = TrainingPrior(list(OCC3D_CLASSES[:FREE]), FREE, SHAPE)
    lab = np.full(SHAPE, FREE)
    lab[16] = OCC3D_CLASSES.index("car")
    prior.add(lab)
    s = score_with_baselines([(truth, wall, None)], BOX_CLASSES, prior)
    assert s["predictors"]["prediction"]["geometry_ray_iou_nonground@1"] == 100.0
    # recall 100; precision below it: wall voxels holding no return that a ray crossed on its way to the next
    # voxel of the same layer are judged free (the grazing cost of a voxel map)
    assert s["predictors"]["prediction"]["voxel_recall_pct"] == 100.0 and s["predictors"]["prediction"]["voxel_f1_pct"] > 85
    assert s["predictors"]["prior"]["voxel_f1_pct"] == 0                          # behind the returns: unjudged
    assert s["predictors"]["prior"]["geometry_ray_iou_nonground@1"] == 100.0     # 0.4 m behind: within 1 m
    assert s["predictors"]["prior"]["object_ray_iou"] > 0 and s["predictors"]["prediction"]["object_ray_iou"] == 0
    assert s["beaten_by"]["object_ray_iou"] == ["prior"]
