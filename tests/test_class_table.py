"""Issue 38: the label table from data (ClassTable), the metric and pictures over a table, the
Occ3D-Waymo ground-truth reader, and the Occ3D-Waymo open-world label-space files."""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.classes import (FREE, OCC3D_CLASSES, OCC3D_COLORS, OCC3D_NUSCENES, OCC3D_WAYMO, ClassTable,
                                 load_class_table)
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.occ3d_waymo import KEYS, Occ3DWaymoLabels, gt_path, list_gt_files
from ago_runtime.pictures import render
from ago_runtime.scoring.metric import OccupancyMetric

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------ the tables
def test_nuscenes_table_is_todays_ids_and_colours():
    t = OCC3D_NUSCENES
    assert t.label_names == list(OCC3D_CLASSES)
    assert t.free_id == FREE == t.free_index and t.is_dense
    assert np.array_equal(t.dense_colors(), OCC3D_COLORS)
    assert np.array_equal(t.palette_by_id(), OCC3D_COLORS)


def test_waymo_table_ids_free_23_and_dense_order():
    t = OCC3D_WAYMO
    assert t.num_classes == 15 and t.free_id == 23 and not t.is_dense
    assert t.id_of("Traffic light") == 5 and t.id_of("walkable") == 14 and t.id_of("general-object") == 0
    dense = t.to_dense(np.array([0, 13, 14, 23, 255], np.uint8))
    assert dense.tolist() == [0, 13, 14, 15, 255]
    with pytest.raises(ValueError, match=r"\[15, 17\]"):
        t.to_dense(np.array([15, 17, 23]))
    pal = t.palette_by_id()
    assert pal.shape == (24, 3) and tuple(pal[23]) == t.colors[-1] and tuple(pal[20]) == (128, 128, 128)


def test_table_rejects_inconsistent_definitions():
    with pytest.raises(ValueError, match="unique"):
        ClassTable("x", ("a", "b"), (0, 0), 2, ((0, 0, 0),) * 3)
    with pytest.raises(ValueError, match="free"):
        ClassTable("x", ("a", "free"), (0, 1), 2, ((0, 0, 0),) * 3)
    with pytest.raises(ValueError, match="ignore"):
        ClassTable("x", ("a",), (0,), 1, ((0, 0, 0),) * 2, ignore_ids=(1,))
    with pytest.raises(ValueError, match="colours"):
        ClassTable("x", ("a",), (0,), 1, ((0, 0, 0),))


def test_load_shipped_and_json_round_trip(tmp_path):
    assert load_class_table("occ3d-waymo") is OCC3D_WAYMO
    assert load_class_table("occ3d_nuscenes") is OCC3D_NUSCENES
    p = tmp_path / "waymo.json"
    p.write_text(json.dumps(OCC3D_WAYMO.to_dict()))
    assert load_class_table(p) == OCC3D_WAYMO
    # colours are optional: distinct hues, free light grey
    q = tmp_path / "mine.json"
    q.write_text(json.dumps({"free_id": 9, "classes": [{"name": "car", "id": 0}, {"name": "road", "id": 3}]}))
    t = load_class_table(q)
    assert t.name == "mine" and t.ids == (0, 3) and t.free_id == 9 and t.colors[0] != t.colors[1]


@pytest.mark.parametrize("content, message", [
    ("[]", "expected a JSON dict"),
    ("{not json", "not valid JSON"),
    ('{"free_id": 3, "classes": []}', "non-empty list"),
    ('{"free_id": 3, "classes": [{"name": "a"}]}', r"classes\[0\]"),
    ('{"free_id": "x", "classes": [{"name": "a", "id": 0}]}', "free_id"),
    ('{"free_id": 0, "classes": [{"name": "a", "id": 0}]}', "unique"),
    ('{"free_id": 1, "classes": [{"name": "a", "id": 0, "color": [0, 0, 300]}]}', "color"),
    ('{"free_id": 1, "classes": [{"name": "a", "id": 0}], "extra": 1}', "unknown keys"),
])
def test_bad_table_files_one_error_naming_the_file(tmp_path, content, message):
    p = tmp_path / "t.json"
    p.write_text(content)
    with pytest.raises(AgoInputError, match=message) as e:
        load_class_table(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_oversized_or_missing_table_file_refused_unread(tmp_path):
    p = tmp_path / "big.json"
    p.write_bytes(b" " * ((1 << 20) + 1))
    with pytest.raises(AgoInputError, match="bytes"):
        load_class_table(p)
    with pytest.raises(AgoInputError, match="not found"):
        load_class_table(tmp_path / "absent.json")


# ------------------------------------------------------------------------------------ the metric
def test_metric_default_unchanged_and_nuscenes_table_identical():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 18, (20, 20, 4)).astype(np.uint8)
    pred = rng.integers(0, 18, (20, 20, 4)).astype(np.uint8)
    mask = rng.random(gt.shape) > 0.3
    a, b = OccupancyMetric(), OccupancyMetric(table=OCC3D_NUSCENES)
    a.update(pred, gt, mask)
    b.update(pred, gt, mask)
    assert np.array_equal(a.confusion, b.confusion) and a.class_names == b.class_names
    assert "class_table" not in a.summary() and b.summary()["class_table"] == "occ3d_nuscenes"


def test_metric_on_waymo_ids_counts_free_23_as_free():
    # GT: a vehicle voxel (1), a road voxel (13), two free voxels (23), one ignored (255)
    gt = np.array([1, 13, 23, 23, 255], np.uint8)
    pred = np.array([1, 23, 23, 13, 4], np.uint8)
    m = OccupancyMetric(table=OCC3D_WAYMO)
    m.update(pred, gt)
    iou = dict(zip(m.class_names, m.iou()))
    assert m.class_names[-1] == "free" and m.free_index == 15
    assert iou["vehicle"] == 1.0
    assert iou["road"] == 0.0                     # road predicted free, free predicted road
    assert iou["free"] == pytest.approx(1 / 3)    # TP 1, FN 1 (-> road), FP 1 (road -> free)
    assert np.isnan(iou["sign"])
    assert m.geometry_iou() == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="does not name"):
        m.update(np.array([17], np.uint8), np.array([1], np.uint8))   # 17 is nuScenes' free, not Waymo's


# ------------------------------------------------------------------------------------ pictures
def test_pictures_take_a_table():
    sem = np.full((6, 6, 3), 23, np.uint8)       # Waymo free everywhere ...
    sem[2, 3, 0] = 13                              # ... a road voxel
    sem[4, 1, 1] = 12                              # ... a tree trunk above the ground
    bev = render.bev_image(sem, table=OCC3D_WAYMO, scale=1, mark_ego=False, height_shading=0.0)
    rows, cols = 6 - 1 - 2, 6 - 1 - 3              # x up, y left (180-degree turn)
    assert tuple(bev[rows, cols]) == OCC3D_WAYMO.colors[13]
    assert tuple(bev[6 - 1 - 4, 6 - 1 - 1]) == OCC3D_WAYMO.colors[12]
    assert tuple(bev[0, 0]) == render.FREE_GREY    # 23 is free with the table ...
    plain = render.bev_image(sem, scale=1, mark_ego=False, height_shading=0.0)
    assert tuple(plain[0, 0]) != render.FREE_GREY  # ... and an unknown class without it
    fig = render.prediction_vs_gt(sem, sem, table=OCC3D_WAYMO, views="bev")
    assert fig.ndim == 3 and fig.shape[2] == 3
    vox = render.voxel_view(sem, table=OCC3D_WAYMO)
    assert (vox != 255).any()


# ------------------------------------------------------------------------------------ the reader
def _write_waymo_gt(path: Path, shape=(8, 8, 4), seed=0, **override):
    rng = np.random.default_rng(seed)
    sem = rng.choice(np.array(list(range(15)) + [23] * 10, np.uint8), size=shape)
    arrays = {"voxel_label": sem, "origin_voxel_state": (rng.random(shape) > 0.3).astype(np.uint8),
              "final_voxel_state": (rng.random(shape) > 0.5).astype(np.uint8),
              "infov": (rng.random(shape) > 0.2).astype(np.uint8)}
    arrays.update(override)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)   # written the way Occ3D's files are: plain np.savez, these four keys
    return arrays


def test_reader_reads_the_layout_as_shipped(tmp_path):
    a = _write_waymo_gt(gt_path(tmp_path, "training", 3, 105))
    b = _write_waymo_gt(gt_path(tmp_path, "training", 3, 7), seed=1)
    _write_waymo_gt(tmp_path / "training" / "003" / "105.npz")            # a 0.1 m file (other grid) beside it
    (tmp_path / "training" / "notes").mkdir()
    assert gt_path(tmp_path, "training", 3, 105) == tmp_path / "training" / "003" / "105_04.npz"
    files = list_gt_files(tmp_path, "training")
    assert [(s, f) for s, f, _ in files] == [(3, 7), (3, 105)]
    assert [(s, f) for s, f, _ in list_gt_files(tmp_path, "training", "0.1")] == [(3, 105)]
    lab = Occ3DWaymoLabels.load(files[1][2], shape=(8, 8, 4))
    assert np.array_equal(lab.semantics, a["voxel_label"]) and np.array_equal(lab.mask_fov, a["infov"])
    assert np.array_equal(lab.mask_camera, a["final_voxel_state"])
    assert np.array_equal(Occ3DWaymoLabels.load(files[0][2]).mask_lidar, b["origin_voxel_state"])
    # round trip through ago's writer gives the same keys and arrays
    out = tmp_path / "copy" / "000_04.npz"
    lab.save(out)
    with np.load(out) as z:
        assert sorted(z.files) == sorted(KEYS)
    assert np.array_equal(Occ3DWaymoLabels.load(out).semantics, lab.semantics)


def test_reader_refuses_bad_files_in_one_line(tmp_path):
    p = tmp_path / "x_04.npz"
    _write_waymo_gt(p, voxel_label=np.full((8, 8, 4), 17, np.uint8))     # nuScenes' free id
    with pytest.raises(AgoInputError, match="does not name"):
        Occ3DWaymoLabels.load(p)
    _write_waymo_gt(p, infov=np.full((8, 8, 4), 2, np.uint8))
    with pytest.raises(AgoInputError, match="'infov' must be a 0/1 mask"):
        Occ3DWaymoLabels.load(p)
    _write_waymo_gt(p, final_voxel_state=np.ones((8, 8, 3), np.uint8))
    with pytest.raises(AgoInputError, match="one 3-D shape"):
        Occ3DWaymoLabels.load(p)
    np.savez(p, semantics=np.zeros((2, 2, 2), np.uint8))                  # an Occ3D-nuScenes labels.npz
    with pytest.raises(AgoInputError, match="missing keys"):
        Occ3DWaymoLabels.load(p)
    _write_waymo_gt(p)
    with pytest.raises(AgoInputError, match="does not match the grid"):
        Occ3DWaymoLabels.load(p, shape=(200, 200, 16))
    p.write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(AgoInputError, match="not a readable npz"):
        Occ3DWaymoLabels.load(p)
    with pytest.raises(AgoInputError, match="split"):
        gt_path(tmp_path, "train", 0, 0)
    with pytest.raises(AgoInputError, match="no such"):
        list_gt_files(tmp_path, "validation")


def test_reader_refuses_a_forged_array_size_before_reading(tmp_path):
    p = tmp_path / "forged_04.npz"
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1,), np.uint8))
    header["shape"] = (100000, 100000, 64)
    with zipfile.ZipFile(p, "w") as zf:
        for key in KEYS:
            with zf.open(f"{key}.npy", "w") as f:
                np.lib.format.write_array_header_1_0(f, header)
                f.write(b"\x00" * 16)
    with pytest.raises(AgoInputError, match="declares"):
        Occ3DWaymoLabels.load(p)


# ------------------------------------------------------------------------------------ label-space files
WAYMO_PROMPTS = ROOT / "prompts" / "waymo"


def _classes_of(path: Path) -> tuple[dict[str, list[str]], list[str], str]:
    """{class: [table classes]}, @known list, @table of a prompt file (read plainly for this check)."""
    classes, known, table = {}, [], ""
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line.startswith("@known:"):
            known = [k.strip() for k in line[7:].split(",") if k.strip()]
        elif line.startswith("@table:"):
            table = line[7:].strip()
        elif line and not line.startswith("@"):
            m = re.match(r"^([^\[\]:]+?)\s*(?:\[([^\]]*)\])?\s*:", line)
            name = m.group(1).strip()
            classes[name] = [c.strip() for c in m.group(2).split(",")] if m.group(2) else [name]
    return classes, known, table


def test_waymo_open_world_files_follow_tab_h():
    pre, pre_known, t1 = _classes_of(WAYMO_PROMPTS / "ow_waymo_pretrain.txt")
    ev, ev_known, t2 = _classes_of(WAYMO_PROMPTS / "ow_waymo.txt")
    assert t1 == t2 == "occ3d_waymo"
    assert list(pre) == ["pedestrian", "road", "sidewalk", "vehicle", "cycle"]
    assert pre["cycle"] == ["bicycle", "motorcycle"]
    assert set(ev_known) == {"pedestrian", "road", "sidewalk", "vehicle"}
    unknown = set(ev) - set(ev_known)
    assert unknown == {"bicycle", "motorcycle", "bicyclist", "sign", "traffic light", "pole", "construction cone",
                       "building", "vegetation", "tree trunk"}
    used = [c for cs in list(pre.values()) + list(ev.values()) for c in cs]
    for c in used:                                   # every class resolves in the Occ3D-Waymo table ...
        OCC3D_WAYMO.id_of(c)
    assert all(OCC3D_WAYMO.id_of(c) != 0 for c in used)   # ... and GO is excluded


def test_ago_show_draws_waymo_files_with_their_table(tmp_path):
    from typer.testing import CliRunner

    from ago_runtime.cli import app

    sem = np.full((8, 8, 4), 23, np.uint8)
    sem[:, :, 0] = 13                                    # road everywhere on the ground
    p = tmp_path / "000_04.npz"
    _write_waymo_gt(p, voxel_label=sem)
    out = tmp_path / "w.png"
    r = CliRunner().invoke(app, ["show", str(p), "--out", str(out), "--view", "bev"])
    assert r.exit_code == 0, r.output
    def magenta(png):   # road (255, 0, 255), darkened by the height shading; nuScenes' id 13 is dark purple
        img = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB).astype(int)
        return ((img[..., 0] > 120) & (img[..., 2] > 120) & (img[..., 1] < 60)).sum()

    assert magenta(out) > 500                            # 32 x 32 BEV pixels of road
    # a plain `semantics` file holding Waymo ids, drawn with --classes
    np.savez(tmp_path / "plain.npz", semantics=sem)
    r = CliRunner().invoke(app, ["show", str(tmp_path / "plain.npz"), "--out", str(out), "--view", "bev",
                                 "--classes", "occ3d_waymo"])
    assert r.exit_code == 0, r.output
    assert magenta(out) > 500
    r = CliRunner().invoke(app, ["show", str(tmp_path / "plain.npz"), "--out", str(out), "--view", "bev"])
    assert r.exit_code == 0 and magenta(out) < 50        # without the table: Occ3D-nuScenes colours
    bad = tmp_path / "bad.json"
    bad.write_text("[1]")
    r = CliRunner().invoke(app, ["show", str(p), "--out", str(tmp_path / "x.png"), "--classes", str(bad)])
    assert isinstance(r.exception, AgoInputError) and not (tmp_path / "x.png").exists()


def test_prompt_files_name_their_class_table():
    """`@table: occ3d_waymo` resolves names and [ids] in the Occ3D-Waymo table and maps its free id (23);
    without it a file means Occ3D-nuScenes as before."""
    from ago_runtime.vocab.prompts import parse_prompt_file, parse_prompt_text

    ev = parse_prompt_file(WAYMO_PROMPTS / "ow_waymo.txt")
    assert ev.table == "occ3d_waymo" and ev.num_classes == 14
    assert ev.classes[ev.index("pedestrian")].occ3d_ids == (OCC3D_WAYMO.id_of("pedestrian"),)   # 2, not nuScenes' 7
    lut = ev.gt_lut(ev.num_classes)
    assert lut[23] == ev.num_classes and lut[0] == 255          # free -> free; GO not scored
    assert lut[13] == ev.index("road")
    pre = parse_prompt_file(WAYMO_PROMPTS / "ow_waymo_pretrain.txt")
    assert pre.classes[pre.index("cycle")].occ3d_ids == (OCC3D_WAYMO.id_of("bicycle"), OCC3D_WAYMO.id_of("motorcycle"))
    nus = parse_prompt_text("pedestrian: pedestrian, person\nroad [driveable_surface]: road\n")
    assert nus.table == "occ3d_nuscenes" and nus.classes[0].occ3d_ids == (7,) and nus.gt_lut(2)[17] == 2
    with pytest.raises(AgoInputError, match=r"line 1: unknown class table 'kitti'"):
        parse_prompt_text("@table: kitti\ncar: car\n")
    with pytest.raises(AgoInputError, match=r"line 2: @table must come before the first class line"):
        parse_prompt_text("car: car\n@table: occ3d_waymo\n")
    with pytest.raises(AgoInputError, match=r"'driveable_surface' is not an occ3d_waymo class name"):
        parse_prompt_text("@table: occ3d_waymo\nroad [driveable_surface]: road\n")


def test_a_waymo_prompt_bank_carries_its_table_to_the_prediction_files(tmp_path):
    """A bank of an `@table: occ3d_waymo` prompt file keeps its table through save/load; the prediction's
    Occ3D-style output is in that table's dense order (free = 15 where the files store 23) with its names."""
    from ago_runtime.classes import OCC3D_WAYMO
    from ago_runtime.predict.predictor import table_id_lookup
    from ago_runtime.vocab.bank import PromptBank, build_bank
    from ago_runtime.vocab.prompts import parse_prompt_file

    space = parse_prompt_file(ROOT / "prompts" / "waymo" / "ow_waymo.txt")

    class Enc:   # a stand-in encoder: what the bank stores does not depend on the vectors
        encoder_id, variant, dim, weights_hash = "test", "test", 4, "0" * 64

        def encode(self, texts):
            rng = np.random.default_rng(len(texts))
            v = rng.normal(size=(len(texts), 4)).astype(np.float32)
            return v / np.linalg.norm(v, axis=1, keepdims=True)

    bank = build_bank(space, Enc())
    assert bank.class_table == OCC3D_WAYMO
    back = PromptBank.load(bank.save(tmp_path / "w.npz"))
    assert back.class_table == OCC3D_WAYMO and json.loads(str(np.load(tmp_path / "w.npz")["meta"][0]))["class_table"] == "occ3d_waymo"
    lut = table_id_lookup(back)
    assert lut[-1] == OCC3D_WAYMO.free_index == 15
    k = back.class_names.index("sidewalk")
    assert OCC3D_WAYMO.label_names[lut[k]] == "walkable"
