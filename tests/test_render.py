"""Tests of ago_runtime.pictures.render (pictures) and the `ago show` verb."""

from __future__ import annotations

import sys
import time

import cv2
import numpy as np
import pytest

from ago_runtime.pictures import render
from ago_runtime.atomic import save_npz
from ago_runtime.classes import FREE, OCC3D_CLASSES, OCC3D_COLORS, OCC3D_ID
from ago_runtime.formats.occ3d import Occ3DLabels

CAR, BUS, TRUCK = OCC3D_ID["car"], OCC3D_ID["bus"], OCC3D_ID["truck"]


def _free(shape=(200, 200, 16)):
    return np.full(shape, FREE, dtype=np.uint8)


def _pixels_of(img, rgb):
    return np.all(img == np.asarray(rgb, dtype=np.uint8), axis=2)


def _read_png(path):
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


# ------------------------------------------------------------------------------- colours
def test_palette_for_known_and_unknown_names():
    names = ["car", "fire hydrant", "vegetation", "lamp post", "free", "kangaroo"]
    pal = render.palette_for(names)
    assert pal.shape == (6, 3) and pal.dtype == np.uint8
    assert np.array_equal(pal[0], OCC3D_COLORS[CAR]) and np.array_equal(pal[2], OCC3D_COLORS[OCC3D_ID["vegetation"]])
    new = pal[[1, 3, 5]]
    assert len({tuple(c) for c in new}) == 3                  # distinct
    assert np.array_equal(render.palette_for(names), pal)     # deterministic
    assert np.array_equal(render.palette_for(list(OCC3D_CLASSES)), OCC3D_COLORS)


# ------------------------------------------------------------------------------- BEV
def test_bev_orientation_forward_up_left_left():
    sem = _free()
    sem[150:160, 100:110, 2:5] = CAR      # x > 0 (in front), y > 0 (left of the ego)
    sem[40:50, 30:40, 2:5] = TRUCK        # behind, right
    img = render.bev_image(sem, scale=1, mark_ego=False, height_shading=0)
    assert img.shape == (200, 200, 3)
    rows, cols = np.nonzero(_pixels_of(img, OCC3D_COLORS[CAR]))
    assert len(rows) == 100 and rows.max() < 100 and cols.max() < 100      # upper-left quadrant
    rows, cols = np.nonzero(_pixels_of(img, OCC3D_COLORS[TRUCK]))
    assert len(rows) == 100 and rows.min() >= 100 and cols.min() >= 100    # lower-right quadrant
    # exact placement: x index i -> row X-1-i, y index j -> column Y-1-j
    assert _pixels_of(img, OCC3D_COLORS[CAR])[200 - 1 - 150, 200 - 1 - 100]


def test_bev_top_voxel_free_unknown_and_mask():
    sem = _free((4, 4, 8))
    sem[0, 0, 1] = CAR
    sem[0, 0, 6] = BUS        # higher: wins
    sem[1, 1, :] = 255        # all unknown
    img = render.bev_image(sem, scale=1, mark_ego=False, height_shading=0)
    assert np.array_equal(img[3, 3], OCC3D_COLORS[BUS])
    assert np.array_equal(img[2, 2], render.UNKNOWN_GREY)
    assert np.array_equal(img[0, 0], render.FREE_GREY)
    mask = np.ones_like(sem, dtype=np.uint8)
    mask[0, 0, 6] = 0         # the bus voxel is not seen
    hidden = render.bev_image(sem, scale=1, mark_ego=False, height_shading=0, mask=mask, mask_mode="hide")
    assert np.array_equal(hidden[3, 3], OCC3D_COLORS[CAR])
    dim = render.bev_image(sem, scale=1, mark_ego=False, height_shading=0, mask=mask)
    assert not np.array_equal(dim[3, 3], OCC3D_COLORS[BUS])  # washed out
    shaded = render.bev_image(sem, scale=1, mark_ego=False, height_shading=0.5)
    assert shaded[3, 3].sum() < img[3, 3].sum()              # lower than the top -> darker


def test_bev_marks_the_ego():
    sem = _free((200, 200, 16))
    img = render.bev_image(sem, scale=2)
    centre = img[195:205, 195:205]
    assert (centre < 60).all(axis=2).any() and (centre == 255).all(axis=2).any()  # black outline, white fill
    assert np.all(render.bev_image(sem, scale=2, mark_ego=False)[195:205, 195:205] == render.FREE_GREY)


# ------------------------------------------------------------------------------- 3-D view
def test_voxel_view_single_cube_faces():
    sem = _free((10, 10, 6))
    sem[5, 5, 2] = CAR
    img = render.voxel_view(sem, scale=6, height_shading=0, edges=False, crop=False, mark_ego=False)
    drawn = np.any(img != render.BACKGROUND, axis=2)
    colours, counts = np.unique(img[drawn], axis=0, return_counts=True)
    assert len(colours) == 3                                  # top and two sides
    bright = colours.sum(axis=1)
    top = colours[np.argmax(bright)]
    assert np.array_equal(top, OCC3D_COLORS[CAR])            # top face: full class colour
    top_rows = np.nonzero(_pixels_of(img, top))[0]
    side_rows = np.nonzero(drawn & ~_pixels_of(img, top))[0]
    assert top_rows.mean() < side_rows.mean()                # top face above the sides


def test_voxel_view_orientation_and_occlusion():
    sem = _free((20, 20, 16))
    sem[15, 10, 0] = CAR       # in front
    sem[2, 10, 0] = TRUCK      # behind
    img = render.voxel_view(sem, scale=3, height_shading=0, edges=False, crop=False, mark_ego=False)
    car_rows = np.nonzero(_pixels_of(img, OCC3D_COLORS[CAR]))[0]
    truck_rows = np.nonzero(_pixels_of(img, OCC3D_COLORS[TRUCK]))[0]
    assert car_rows.mean() < truck_rows.mean()                # forward is up the page
    sem = _free((20, 20, 16))
    sem[10, 17, 0] = CAR       # left
    sem[10, 2, 0] = TRUCK      # right
    img = render.voxel_view(sem, scale=3, height_shading=0, edges=False, crop=False, mark_ego=False)
    assert np.nonzero(_pixels_of(img, OCC3D_COLORS[CAR]))[1].mean() < \
        np.nonzero(_pixels_of(img, OCC3D_COLORS[TRUCK]))[1].mean()

    # a wall between the viewer (behind-right, above) and a voxel hides it: z-buffer, not draw order
    sem = _free((10, 16, 16))
    sem[3, :, :] = BUS
    sem[5, 5, 2] = CAR
    img = render.voxel_view(sem, scale=3, height_shading=0, edges=False, mark_ego=False)
    assert not _pixels_of(img, OCC3D_COLORS[CAR]).any()
    sem[3, :, :] = FREE
    img = render.voxel_view(sem, scale=3, height_shading=0, edges=False, mark_ego=False)
    assert _pixels_of(img, OCC3D_COLORS[CAR]).any()


def test_voxel_view_mask_washes_out_and_empty_volume():
    sem = _free((10, 10, 6))
    sem[5, 5, 2] = CAR
    mask = np.zeros(sem.shape, dtype=np.uint8)
    img = render.voxel_view(sem, scale=4, height_shading=0, edges=False, mask=mask, mark_ego=False)
    assert not _pixels_of(img, OCC3D_COLORS[CAR]).any()
    empty = render.voxel_view(_free((10, 10, 6)), mark_ego=False)
    assert empty.ndim == 3 and np.all(empty == render.BACKGROUND)


# ------------------------------------------------------------------------------- scalars, layout
def test_scalar_bev():
    vol = np.zeros((50, 40, 4))
    vol[45, 20, 1] = 1.0                       # high value in front
    mask = np.ones(vol.shape, dtype=bool)
    mask[:, :5] = False                        # right edge columns never seen
    img = render.scalar_bev(vol, mask=mask, scale=2, label="entropy")
    assert img.shape[0] == 100 and img.shape[1] > 80 and img.dtype == np.uint8
    yellow = img[:100, :80].astype(int)
    r, c = np.unravel_index(np.argmax(yellow.sum(axis=2) * (yellow[..., 2] < 100)), yellow.shape[:2])
    assert r < 20                              # viridis' yellow (max) near the top
    assert np.all(img[:100, 80 - 10:80][::7, ::3] == render.UNKNOWN_GREY)  # y < -38 m never seen: right edge
    mean_img = render.scalar_bev(vol, reduce="mean", scale=2, vmin=0, vmax=1)
    assert mean_img.shape == img.shape
    with pytest.raises(ValueError):
        render.scalar_bev(vol, reduce="median")


def test_layout_helpers():
    a = np.zeros((50, 30, 3), dtype=np.uint8)
    b = np.full((80, 20, 3), 200, dtype=np.uint8)
    out = render.side_by_side([("a", a), ("b", b)], gap=8)
    assert out.shape[1] == 30 + 8 + 20 and out.shape[0] > 80
    lg = render.legend(["car", "bus", "terrain"], OCC3D_COLORS[[CAR, BUS, OCC3D_ID["terrain"]]], width=300)
    assert lg.shape[1] == 300 and _pixels_of(lg, OCC3D_COLORS[BUS]).sum() > 20
    v = render.stack_vertical([a, b], gap=4)
    assert v.shape == (50 + 4 + 80, 30, 3)


def test_rig_mosaic_layout():
    names = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
    colours = {n: np.array([20 * i + 10, 100, 250 - 30 * i], dtype=np.uint8) for i, n in enumerate(names)}
    images = {n: np.broadcast_to(c, (90, 160, 3)).copy() for n, c in colours.items()}
    out = render.rig_mosaic(images, width=960)
    assert out.shape == (2 * 180, 960, 3)
    for r, row in enumerate(render.RIG_LAYOUT):
        for c, name in enumerate(row):
            assert np.array_equal(out[r * 180 + 150, c * 320 + 160], colours[name]), name
    del images["CAM_BACK"]
    out = render.rig_mosaic(images, width=960, layout=render.RIG_LAYOUT)
    assert np.all(out[180 + 170, 320 + 300] == 40)


def test_rig_mosaic_of_another_rig_keeps_each_aspect():
    """Waymo's five cameras (two heights): rows of three in the rig's order; the shorter side images keep
    their aspect (padded dark below, not stretched)."""
    names = ["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"]
    assert render.mosaic_layout(names) == (("FRONT", "FRONT_LEFT", "FRONT_RIGHT"), ("SIDE_LEFT", "SIDE_RIGHT"))
    images = {n: np.full((100 if n.startswith("FRONT") else 70, 150, 3), 30 * i + 60, np.uint8)
              for i, n in enumerate(names)}
    out = render.rig_mosaic(images, width=900)
    assert out.shape == (200 + 140, 900, 3)
    assert np.all(out[200 + 130, 300 + 150] == 30 * 4 + 60)        # SIDE_RIGHT's own pixels up to its height
    assert np.all(out[200 + 130, 600 + 150] == 255)                # no third tile on the second row
    assert render.mosaic_layout(["FRONT"]) == (("FRONT",),)


def test_save_png_rgb_roundtrip(tmp_path):
    img = np.zeros((4, 5, 3), dtype=np.uint8)
    img[..., 0] = 255                          # pure red
    p = render.save_png(tmp_path / "sub" / "red.png", img)
    bgr = cv2.imread(str(p))
    assert bgr.shape == (4, 5, 3) and np.all(bgr[..., 2] == 255) and np.all(bgr[..., 0] == 0)
    assert sorted(x.name for x in (tmp_path / "sub").iterdir()) == ["red.png"]  # no temp left over


def test_prediction_vs_gt_any_label_space():
    names = ["ground", "thing", "free"]
    gt = np.full((30, 30, 5), 2, dtype=np.uint8)
    gt[:, :, 0] = 0
    gt[10:14, 10:14, 1:3] = 1
    pred = gt.copy()
    pred[10:14, 10:14, 1:3] = 0
    fig = render.prediction_vs_gt(pred, gt, class_names=names, free_index=2)
    pal = render.palette_for(names)
    assert fig.ndim == 3 and _pixels_of(fig, pal[1]).any() and _pixels_of(fig, pal[0]).any()
    with pytest.raises(ValueError):
        render.prediction_vs_gt(pred[:10], gt, class_names=names, free_index=2)


# ------------------------------------------------------------------------------- the real frame
def test_real_frame_pictures(occ3d_sample_labels, tmp_path):
    lab = Occ3DLabels.load(occ3d_sample_labels)
    bev = render.bev_image(lab.semantics, scale=3, height_shading=0)
    t0 = time.perf_counter()
    vox = render.voxel_view(lab.semantics, height_shading=0, edges=False)
    seconds = time.perf_counter() - t0
    assert seconds < 5.0
    render.save_png(tmp_path / "bev.png", bev)
    render.save_png(tmp_path / "vox.png", vox)
    bev_back, vox_back = _read_png(tmp_path / "bev.png"), _read_png(tmp_path / "vox.png")
    assert bev_back.shape == (600, 600, 3) and np.array_equal(bev_back, bev)
    assert vox_back.shape[0] > 300 and vox_back.shape[1] > 600
    present = [c for c in np.unique(lab.semantics) if c < FREE]
    for img in (bev_back, vox_back):
        seen = [c for c in present if _pixels_of(img, OCC3D_COLORS[c]).sum() >= 5]
        assert len(seen) >= 5, seen
    fig = render.prediction_vs_gt(lab.semantics, lab.semantics, lab.mask_camera)
    assert fig.shape[1] >= 2 * vox.shape[1]


# ------------------------------------------------------------------------------- `ago show`
def _run_cli(monkeypatch, *args):
    from ago_runtime.cli import main

    monkeypatch.setattr(sys, "argv", ["ago", *args])
    try:
        main()
    except SystemExit as e:
        return e.code or 0
    return 0


def test_cli_show(tmp_path, monkeypatch, capsys):
    sem = _free((40, 40, 8))
    sem[30:34, 20:24, 1:3] = CAR
    mask = np.ones(sem.shape, dtype=np.uint8)
    Occ3DLabels(sem, mask, mask).save(tmp_path / "gt.npz")
    pred = sem.copy()
    pred[30:34, 20:24, 1:3] = TRUCK
    save_npz(tmp_path / "pred.npz", semantics=pred)
    assert _run_cli(monkeypatch, "show", str(tmp_path / "gt.npz"), "--out", str(tmp_path / "a.png")) == 0
    a = _read_png(tmp_path / "a.png")
    assert _pixels_of(a, OCC3D_COLORS[CAR]).any()
    assert _run_cli(monkeypatch, "show", str(tmp_path / "pred.npz"), "--gt", str(tmp_path / "gt.npz"),
                    "--view", "bev", "--out", str(tmp_path / "b.png")) == 0
    b = _read_png(tmp_path / "b.png")
    assert _pixels_of(b, OCC3D_COLORS[CAR]).any() and _pixels_of(b, OCC3D_COLORS[TRUCK]).any()
    assert "wrote" in capsys.readouterr().out


def test_cli_show_bad_input_exit_2(tmp_path, monkeypatch, capsys):
    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"\x00garbage")
    assert _run_cli(monkeypatch, "show", str(bad), "--out", str(tmp_path / "x.png")) == 2
    assert "broken.npz" in capsys.readouterr().err
    flat = tmp_path / "flat.npz"
    save_npz(flat, semantics=np.zeros((10, 10), dtype=np.uint8))
    assert _run_cli(monkeypatch, "show", str(flat), "--out", str(tmp_path / "x.png")) == 2
    err = capsys.readouterr().err
    assert "flat.npz" in err and "3-D" in err
    assert not (tmp_path / "x.png").exists()


def _tiny_dataset(root):
    from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
    from ago_runtime.formats.nuscenes_writer import NuScenesWriter

    rig = Rig.nuscenes_like(160, 90)
    colours = {n: np.array([40 * i + 20, 200 - 30 * i, 90], dtype=np.uint8) for i, n in enumerate(CAMERA_NAMES)}
    images = {n: np.broadcast_to(c, (90, 160, 3)).copy() for n, c in colours.items()}
    sem = _free()
    sem[120:130, 90:100, 2:6] = BUS
    mask = np.ones(sem.shape, dtype=np.uint8)
    writer = NuScenesWriter(root)
    scene = writer.add_scene("scene-0001")
    token = writer.add_sample(scene, 1_000_000, np.eye(4), rig, images,
                              np.zeros((10, 5), dtype=np.float32), np.eye(4), gt=Occ3DLabels(sem, mask, mask))
    writer.close({"val": ["scene-0001"]})
    return token, colours


def test_cli_show_dataset_rig(tmp_path, monkeypatch, capsys):
    token, colours = _tiny_dataset(tmp_path / "ds")
    out = tmp_path / "rig.png"
    assert _run_cli(monkeypatch, "show", str(tmp_path / "ds"), "--sample", token, "--out", str(out)) == 0
    img = _read_png(out)
    for name, c in colours.items():  # JPEG: allow a small error
        close = np.all(np.abs(img.astype(int) - c.astype(int)) <= 6, axis=2)
        assert close.sum() > 1000, name
    r, g, b = (img[..., i].astype(int) for i in range(3))
    assert np.sum((r == g) & (r > 100) & (b == 0)) > 100  # the bus (yellow, height-shaded) in the GT BEV
    assert _run_cli(monkeypatch, "show", str(tmp_path / "ds"), "--index", "0", "--out", str(out)) == 0
    capsys.readouterr()
    assert _run_cli(monkeypatch, "show", str(tmp_path / "ds"), "--index", "5", "--out", str(out)) == 2
    assert "out of range" in capsys.readouterr().err
    assert _run_cli(monkeypatch, "show", str(tmp_path / "ds"), "--sample", "nope", "--out", str(out)) == 2
    assert "nope" in capsys.readouterr().err
    assert _run_cli(monkeypatch, "show", str(tmp_path / "ds"), "--out", str(out)) == 2
