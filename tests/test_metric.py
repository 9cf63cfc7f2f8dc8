"""Tests of ago_runtime.scoring.metric (Occ3D mIoU semantics) and the `ago metric` verb."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from ago_runtime.atomic import save_npz
from ago_runtime.classes import FREE, OCC3D_CLASSES
from ago_runtime.scoring.metric import OccupancyMetric, upsample_nearest
from ago_runtime.formats.occ3d import Occ3DLabels

ABF = ["a", "b", "free"]  # a tiny label space: two classes + free at 2


def _metric3():
    return OccupancyMetric(ABF, free_index=2)


# ------------------------------------------------------------------------------- hand-made cases
def test_confusion_and_iou_worked_by_hand():
    gt = np.array([0, 0, 0, 1, 1, 2, 2, 2], dtype=np.uint8)
    pred = np.array([0, 0, 1, 1, 2, 2, 0, 2], dtype=np.uint8)
    m = _metric3()
    m.update(pred, gt)
    # rows = GT, columns = prediction
    assert m.confusion.tolist() == [[2, 1, 0], [0, 1, 1], [1, 0, 2]]
    # a: 2 / (3 + 3 - 2); b: 1 / (2 + 2 - 1); free: 2 / (3 + 3 - 2)
    np.testing.assert_allclose(m.iou(), [0.5, 1 / 3, 0.5])
    assert m.miou() == pytest.approx((0.5 + 1 / 3) / 2)          # free not in the mean
    # occupied = {a, b}: TP 4 (a<->b confusions still count as occupied), FN 1, FP 1
    assert m.geometry_iou() == pytest.approx(4 / 6)
    assert m.miou(["b"]) == pytest.approx(1 / 3)


def test_mask_is_used_as_bool_not_as_indices():
    gt = np.array([0, 0, 0, 1, 1, 2, 2, 2], dtype=np.uint8)
    pred = np.array([0, 0, 1, 1, 2, 2, 0, 2], dtype=np.uint8)
    mask_u8 = np.array([1, 1, 1, 1, 1, 0, 0, 0], dtype=np.uint8)  # as stored in labels.npz
    m = _metric3()
    m.update(pred, gt, mask_u8)
    # Only the first five voxels count. (Indexing with the uint8 mask would instead pick
    # voxels 1,1,1,1,1,0,0,0 -> eight entries, all GT a.)
    assert m.confusion.sum() == 5
    assert m.confusion.tolist() == [[2, 1, 0], [0, 1, 1], [0, 0, 0]]
    np.testing.assert_allclose(m.iou(), [2 / 3, 1 / 3, 0.0])
    wrong = _metric3()
    wrong.update(pred[mask_u8], gt[mask_u8])  # what the bug would compute
    assert not np.array_equal(wrong.confusion, m.confusion)


def test_absent_class_is_nan_not_one_and_left_out_of_means():
    m = OccupancyMetric(["a", "b", "c", "free"], free_index=3)
    gt = np.array([0, 0, 1, 3, 3])
    pred = np.array([0, 0, 3, 3, 3])
    m.update(pred, gt)
    iou = m.iou()
    assert iou[0] == 1.0 and iou[1] == 0.0  # b present in GT, never predicted -> 0
    assert np.isnan(iou[2])                 # c absent everywhere -> NaN, never 1
    assert m.miou() == pytest.approx(0.5)   # nanmean(1, 0)
    assert np.isnan(m.miou(["c"]))
    s = m.summary()
    assert s["iou"]["c"] is None and s["mIoU"] == 50.0
    json.dumps(s, allow_nan=False)  # JSON-able, no NaN
    assert "| c | n/a |" in m.to_markdown()


def test_class_only_predicted_scores_zero():
    m = _metric3()
    m.update(np.array([1, 2]), np.array([2, 2]))
    assert m.iou()[1] == 0.0 and np.isnan(m.iou()[0])


def test_ignore_label_in_gt_is_skipped():
    m = _metric3()
    m.update(np.array([0, 1, 1]), np.array([0, 255, 255]))
    assert m.confusion.sum() == 1 and m.iou()[0] == 1.0


def test_split_confusion_is_summed_not_frame_averaged():
    m = _metric3()
    m.update(np.array([0]), np.array([0]))            # frame IoU(a) = 1
    m.update(np.array([2, 2, 2]), np.array([0, 0, 0]))  # frame IoU(a) = 0
    assert m.frames == 2
    assert m.iou()[0] == pytest.approx(1 / 4)         # not (1 + 0) / 2


def test_merge_equals_single_pass():
    rng = np.random.default_rng(0)
    gts = [rng.integers(0, 3, size=(4, 5, 3)) for _ in range(4)]
    preds = [rng.integers(0, 3, size=(4, 5, 3)) for _ in range(4)]
    masks = [rng.random((4, 5, 3)) > 0.3 for _ in range(4)]
    whole, part1, part2 = _metric3(), _metric3(), _metric3()
    for i, (p, g, k) in enumerate(zip(preds, gts, masks)):
        whole.update(p, g, k)
        (part1 if i < 2 else part2).update(p, g, k)
    part1.merge(part2)
    assert np.array_equal(part1.confusion, whole.confusion) and part1.frames == 4
    with pytest.raises(ValueError):
        part1.merge(OccupancyMetric())


def test_bad_inputs_are_refused():
    m = _metric3()
    with pytest.raises(ValueError, match="shape"):
        m.update(np.zeros((2, 2, 2)), np.zeros((2, 2, 1)))
    with pytest.raises(ValueError, match="labels"):
        m.update(np.array([3]), np.array([0]))        # label beyond the space
    with pytest.raises(ValueError, match="labels"):
        m.update(np.array([0]), np.array([7]))
    with pytest.raises(KeyError):
        m.miou(["no-such-class"])


def test_miou_variants_on_occ3d_space():
    m = OccupancyMetric()  # Occ3D: 17 classes + free at 17
    assert m.free_index == FREE and m.num_labels == 18
    # every class predicted right once; `others` (0) and `other_flat` (12) always predicted free
    gt = np.concatenate([np.arange(17), [0, 12]])
    pred = np.concatenate([np.arange(17), [FREE, FREE]])
    pred[0] = FREE
    pred[12] = FREE
    m.update(pred, gt)
    iou = m.iou()
    assert iou[0] == 0 and iou[12] == 0 and np.all(iou[[i for i in range(17) if i not in (0, 12)]] == 1)
    assert m.miou() == pytest.approx(15 / 17)
    assert m.miou_1_16() == pytest.approx(15 / 16)
    assert m.miou_star() == pytest.approx(1.0)
    s = m.summary()
    assert s["mIoU_star"] == 100.0 and s["mIoU_1_16"] == round(1500 / 16, 2)


def test_geometry_iou_nan_when_nothing_occupied():
    m = _metric3()
    m.update(np.array([2, 2]), np.array([2, 2]))
    assert np.isnan(m.geometry_iou())


def test_upsample_nearest():
    v = np.arange(8, dtype=np.uint8).reshape(2, 2, 2)
    u = upsample_nearest(v, (2, 3, 1))
    assert u.shape == (4, 6, 2) and u.dtype == np.uint8
    assert u[3, 5, 1] == v[1, 1, 1] and u[0, 2, 0] == v[0, 0, 0] and u[2, 3, 0] == v[1, 1, 0]
    assert upsample_nearest(v, 2).shape == (4, 4, 4)


# ------------------------------------------------------------------------------- the real frame
def _brute_force_iou(pred, gt, mask, n_labels):
    """Independent per-class loop (no confusion matrix)."""
    valid = mask.astype(bool) & (gt != 255)
    out = []
    for c in range(n_labels):
        tp = np.sum((pred == c) & (gt == c) & valid)
        fp = np.sum((pred == c) & (gt != c) & valid)
        fn = np.sum((pred != c) & (gt == c) & valid)
        out.append(tp / (tp + fp + fn) if tp + fp + fn else np.nan)
    return np.array(out)


def test_real_frame_gt_vs_itself_and_vs_free(occ3d_sample_labels):
    lab = Occ3DLabels.load(occ3d_sample_labels)
    assert lab.mask_camera.dtype == np.uint8  # stored as 0/1: the metric must turn it into bool
    present = np.unique(lab.semantics[lab.mask_camera.astype(bool)])
    present = [int(c) for c in present if c < FREE]
    assert len(present) >= 5

    same = OccupancyMetric()
    same.update(lab.semantics, lab.semantics, lab.mask_camera)
    iou = same.iou()
    assert np.all(iou[present] == 1.0)
    absent = [c for c in range(17) if c not in present]
    assert np.all(np.isnan(iou[absent]))
    assert same.miou() == 1.0 and same.geometry_iou() == 1.0
    assert same.confusion.sum() == int(lab.mask_camera.sum())

    free = OccupancyMetric()
    free.update(np.full_like(lab.semantics, FREE), lab.semantics, lab.mask_camera)
    assert np.all(free.iou()[present] == 0.0)
    assert free.miou() == 0.0 and free.geometry_iou() == 0.0


def test_real_frame_against_brute_force(occ3d_sample_labels):
    lab = Occ3DLabels.load(occ3d_sample_labels)
    rng = np.random.default_rng(1)
    pred = lab.semantics.copy()
    flip = rng.random(pred.shape) < 0.1
    pred[flip] = rng.integers(0, 18, size=int(flip.sum()))
    m = OccupancyMetric()
    m.update(pred, lab.semantics, lab.mask_camera)
    expected = _brute_force_iou(pred, lab.semantics, lab.mask_camera, 18)
    np.testing.assert_allclose(m.iou(), expected, equal_nan=True)
    assert m.miou() == pytest.approx(np.nanmean(expected[:17]))
    # passing the uint8 mask or the bool mask gives the same counts
    m2 = OccupancyMetric()
    m2.update(pred, lab.semantics, lab.mask_camera.astype(bool))
    assert np.array_equal(m.confusion, m2.confusion)
    # geometry IoU by brute force
    valid = lab.mask_camera.astype(bool)
    occ_p, occ_g = pred[valid] != FREE, lab.semantics[valid] != FREE
    assert m.geometry_iou() == pytest.approx((occ_p & occ_g).sum() / (occ_p | occ_g).sum())


# ------------------------------------------------------------------------------- `ago metric`
def _run_cli(monkeypatch, *args):
    from ago_runtime.cli import main

    monkeypatch.setattr(sys, "argv", ["ago", *args])
    try:
        main()
    except SystemExit as e:
        return e.code or 0
    return 0


def _make_split(tmp_path, rng, shape=(8, 8, 4)):
    gt_root, pred_root = tmp_path / "gts", tmp_path / "pred"
    frames = []
    for i in range(3):
        sem = rng.integers(0, 18, size=shape).astype(np.uint8)
        mask = (rng.random(shape) > 0.3).astype(np.uint8)
        token = f"tok{i}"
        Occ3DLabels(sem, mask, mask).save(gt_root / "scene-0001" / token / "labels.npz")
        pred = sem.copy()
        pred[rng.random(shape) < 0.3] = 17
        frames.append((token, sem, mask, pred))
    # one nested prediction, one flat, one flat at half resolution
    save_npz(pred_root / "scene-0001" / "tok0" / "labels.npz", semantics=frames[0][3])
    save_npz(pred_root / "tok1.npz", semantics=frames[1][3])
    coarse = frames[2][3][::2, ::2, ::2]
    save_npz(pred_root / "tok2.npz", semantics=coarse)
    expected = OccupancyMetric()
    for k, (token, sem, mask, pred) in enumerate(frames):
        p = upsample_nearest(coarse, 2) if k == 2 else pred
        expected.update(p, sem, mask.astype(bool))
    return gt_root, pred_root, expected


def test_cli_metric_json_and_markdown(tmp_path, monkeypatch, capsys):
    gt_root, pred_root, expected = _make_split(tmp_path, np.random.default_rng(2))
    rc = _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root),
                  "--json", str(tmp_path / "m.json"), "--md", str(tmp_path / "m.md"),
                  "--subset", "vehicles=car,truck,bus")
    assert rc == 0
    got = json.loads((tmp_path / "m.json").read_text())
    want = expected.summary()
    assert got["confusion"] == want["confusion"] and got["frames"] == 3
    assert got["mIoU"] == want["mIoU"] and got["geometry_IoU"] == want["geometry_IoU"]
    assert got["subsets"]["vehicles"]["mIoU"] == round(expected.miou(["car", "truck", "bus"]) * 100, 2)
    md = (tmp_path / "m.md").read_text()
    assert "mIoU (vehicles)" in md and md in capsys.readouterr().out


def test_cli_metric_bad_inputs_exit_2(tmp_path, monkeypatch, capsys):
    gt_root, pred_root, _ = _make_split(tmp_path, np.random.default_rng(3))
    bad = pred_root / "tok1.npz"
    bad.write_bytes(b"this is not a zip file")
    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root)) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "tok1.npz" in err

    save_npz(bad, semantics=np.zeros((8, 8), dtype=np.uint8))  # wrong shape
    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root)) == 2
    assert "tok1.npz" in capsys.readouterr().err

    bad.unlink()  # a missing prediction
    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root)) == 2
    assert "no prediction" in capsys.readouterr().err
    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root), "--allow-missing") == 0
    capsys.readouterr()

    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root),
                    "--subset", "x=car,flying_saucer", "--allow-missing") == 2
    assert "flying_saucer" in capsys.readouterr().err


def test_class_table_is_occ3d():
    assert OccupancyMetric().class_names == list(OCC3D_CLASSES)


def test_cli_metric_in_a_prompt_files_space(tmp_path, monkeypatch):
    """--prompts: GT of classes outside the prompt file is ignored (as ago eval does), predictions are
    matched by class name, and the @known line gives known / unknown subsets."""
    shape = (4, 4, 2)
    sem = np.full(shape, 17, np.uint8)
    sem[0] = 11   # driveable_surface
    sem[1] = 12   # other_flat: not in the prompt file
    sem[2, :2] = 4  # car
    gt_root, pred_root = tmp_path / "gt", tmp_path / "pred"
    mask = np.ones(shape, np.uint8)
    Occ3DLabels(sem, mask, mask).save(gt_root / "scene-0001" / "tok0" / "labels.npz")
    pred = sem.copy()
    pred[1] = 11        # other_flat GT predicted as driveable surface: only counts without --prompts
    save_npz(pred_root / "tok0.npz", semantics=pred, class_names=np.array(OCC3D_CLASSES, dtype=str))
    prompts = tmp_path / "p.txt"
    prompts.write_text("@name: t\n@known: driveable_surface\ncar: car\ndriveable_surface: driveable surface\n")
    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root),
                    "--json", str(tmp_path / "plain.json")) == 0
    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root), "--prompts", str(prompts),
                    "--json", str(tmp_path / "space.json")) == 0
    plain = json.loads((tmp_path / "plain.json").read_text())
    space = json.loads((tmp_path / "space.json").read_text())
    assert plain["iou"]["driveable_surface"] == 50.0
    assert space["iou"]["driveable_surface"] == 100.0 and space["iou"]["car"] == 100.0
    assert space["subsets"]["known"]["mIoU"] == 100.0 and space["subsets"]["unknown"]["classes"] == ["car"]
    # a prediction of a class the prompt file does not have is refused, naming the file
    pred[3] = 9  # truck
    save_npz(pred_root / "tok0.npz", semantics=pred, class_names=np.array(OCC3D_CLASSES, dtype=str))
    assert _run_cli(monkeypatch, "metric", "--pred", str(pred_root), "--gt", str(gt_root), "--prompts", str(prompts)) == 2
