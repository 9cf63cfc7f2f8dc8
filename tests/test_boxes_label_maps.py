"""`ago pseudo-labels --segmenter boxes --write-masks DIR` (issue 35): the boxes segmenter's label maps
written in the layout of docs/vlm_files.md and read back by the file backend. Tests on ../shared skip
when it is absent."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_path
from test_bad_inputs import assert_one_error_line, run_ago


def scene_root() -> Path:
    return shared_path("nuscenes-scene")


@pytest.fixture(scope="module")
def scene_frame():
    from ago_runtime.formats.nuscenes import NuScenesDataset

    root = scene_root()
    return root, NuScenesDataset(root, load_images=False, load_extras=False)[3]


def test_written_maps_read_back_by_the_file_backend(tmp_path, scene_frame):
    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
    from ago_train.pseudo.backends import FileSegmenter, image_stem
    from ago_train.pseudo.boxes import BoxSegmenter

    root, frame = scene_frame
    space = parse_prompt_file(resolve_prompt_file("cw"))
    masks = tmp_path / "masks"
    boxes = BoxSegmenter(root, space, masks_out=masks)
    assert not masks.exists()                      # nothing written before the first map
    painted = {cam.name: boxes.segment(frame, cam.name) for cam in frame.rig}
    # the documented layout: classes.json + <camera>/<image stem>.png, 8-bit, image size, 0 = no label
    classes = json.loads((masks / "classes.json").read_text())
    assert classes["1"] == space.classes[0].name and "0" not in classes
    files = FileSegmenter(masks, space)
    for cam in frame.rig:
        png = masks / cam.name / f"{image_stem(frame, cam.name)}.png"
        assert png.is_file() and Path(frame.image_paths[cam.name]).stem == png.stem
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint8 and raw.shape == (cam.height, cam.width)
        assert ((raw == 0) == (painted[cam.name] == 255)).all()   # no label <-> id 0
        np.testing.assert_array_equal(files.segment(frame, cam.name), painted[cam.name])
    car = space.class_names.index("car")
    assert any((m == car).any() for m in painted.values())      # a map with something in it was compared


def test_a_folder_of_other_ids_is_refused(tmp_path, scene_frame):
    from ago_runtime.errors import AgoInputError
    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
    from ago_train.pseudo.boxes import BoxSegmenter

    root, _ = scene_frame
    space = parse_prompt_file(resolve_prompt_file("cw"))
    (tmp_path / "masks").mkdir()
    (tmp_path / "masks" / "classes.json").write_text(json.dumps({"1": "road"}))
    with pytest.raises(AgoInputError, match="classes.json"):
        BoxSegmenter(root, space, masks_out=tmp_path / "masks")


def test_pseudo_labels_from_written_maps_equal_the_boxes_ones(tmp_path):
    """The whole round trip through the CLI: boxes -> label-map files -> `--segmenter files` -> the same
    pseudo-labels, voxel for voxel."""
    root = scene_root()
    common = ["--data", str(root), "--shard", "20/41", "--keyframes", "2"]
    r = run_ago(["pseudo-labels", *common, "--out", "pl_boxes", "--segmenter", "boxes",
                 "--write-masks", "masks"], tmp_path)
    assert r.code == 0, r.stderr
    pngs = list((tmp_path / "masks").rglob("*.png"))
    assert len(pngs) >= 6                          # the keyframe's cameras and its neighbour's that saw points
    r = run_ago(["pseudo-labels", *common, "--out", "pl_files", "--segmenter", "files", "--masks", "masks"], tmp_path)
    assert r.code == 0, r.stderr
    a = sorted((tmp_path / "pl_boxes").rglob("labels.npz"))
    b = sorted((tmp_path / "pl_files").rglob("labels.npz"))
    assert len(a) == len(b) == 1 and a[0].relative_to(tmp_path / "pl_boxes") == b[0].relative_to(tmp_path / "pl_files")
    la, lb = np.load(a[0]), np.load(b[0])
    for key in ("semantics", "mask_lidar", "mask_camera"):
        np.testing.assert_array_equal(la[key], lb[key])
    assert (la["semantics"] < 17).sum() > 100       # labelled voxels were compared, not two empty grids
    meta = json.loads((tmp_path / "pl_files" / "meta.json").read_text())
    assert meta["segmenter"]["name"] == "files"


def test_write_masks_only_with_the_boxes_segmenter(tmp_path):
    r = run_ago(["pseudo-labels", "--data", str(scene_root()), "--out", "o", "--segmenter", "files",
                 "--masks", "m", "--write-masks", "w"], tmp_path)
    assert_one_error_line(r, "--write-masks", "--segmenter boxes")
    assert not (tmp_path / "o").exists() and not (tmp_path / "w").exists()
