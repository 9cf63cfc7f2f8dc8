"""Pseudo-labels and VLM embeddings lifted to 3-D (ago_train/pseudo): geometry, voting, backends, driver."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
from ago_runtime.classes import FREE, IGNORE, NUM_SEMANTIC, OCC3D_ID
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.frame import Frame, LidarSweep
from ago_runtime.geometry.grid import Grid
from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
from ago_train.pseudo.aggregate import lift_frame, warp_to
from ago_train.pseudo.backends import FileImageEmbedder, FileSegmenter
from ago_train.pseudo.generate import (PseudoLabelConfig, PseudoLabelDir, build_sample, generate,
                                       load_pseudo_labels, load_voxel_embeds)
from ago_train.pseudo.lift import assign_cameras, lift_labels, sample_bilinear
from ago_train.pseudo.raycast import GrazingRule, grazing_stops, occupied_keys, traverse
from ago_train.pseudo.simulated import (SimEmbedderConfig, SimSegmenterConfig, SimulatedImageEmbedder,
                                        SimulatedSegmenter, similarity_stats)
from ago_train.pseudo.voting import FeatureMean, vote

W, H = 160, 90


# ---------------------------------------------------------------------------------------------
# helpers: hand-made frames and a tiny in-memory dataset
# ---------------------------------------------------------------------------------------------
def pose(yaw_deg: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = np.deg2rad(yaw_deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    m[:3, 3] = t
    return m


LIDAR2EGO = pose(0.0, (0.9, 0.0, 1.8))


def make_frame(points_lidar: np.ndarray, ego2global=None, token="t0", scene="scene-a", extras=None) -> Frame:
    ego2global = np.eye(4) if ego2global is None else ego2global
    pts = np.zeros((len(points_lidar), 5), np.float32)
    pts[:, :3] = points_lidar
    sweep = LidarSweep(pts, LIDAR2EGO.copy(), ego2global, 0, f"{token}.bin")
    rig = Rig.nuscenes_like(W, H)
    paths = {c: f"/data/samples/{c}/{token}__{c}.jpg" for c in CAMERA_NAMES}
    return Frame(token=token, scene=scene, timestamp=0, rig=rig, ego2global=ego2global, image_paths=paths,
                 sweeps=[sweep], extras=extras or {})


def ego_to_lidar(points_ego: np.ndarray) -> np.ndarray:
    m = np.linalg.inv(LIDAR2EGO)
    return points_ego @ m[:3, :3].T + m[:3, 3]


class ConstantSegmenter:
    """Every pixel of every image gets one label (per frame token)."""

    name = "constant"

    def __init__(self, label_by_token: dict[str, int]):
        self.label_by_token = label_by_token

    def config_dict(self):
        return {"labels": self.label_by_token}

    def segment(self, frame, camera):
        cam = frame.rig[camera]
        return np.full((cam.height, cam.width), self.label_by_token[frame.token], np.uint8)


class ListDataset:
    """The slice of NuScenesDataset the driver uses, over a list of frames of one scene."""

    def __init__(self, frames):
        self.frames = frames
        self.sample_tokens = [f.token for f in frames]

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        f = self.frames[i]
        return Frame(f.token, f.scene, f.timestamp, f.rig, f.ego2global, dict(f.images), dict(f.image_paths),
                     list(f.sweeps), f.gt, dict(f.extras))

    def scene_of(self, i):
        return self.frames[i].scene

    def neighbours(self, i, count, interval):
        out, k = [], 1
        while len(out) < count and (i + k * interval < len(self) or i - k * interval >= 0):
            for j in (i + k * interval, i - k * interval):
                if 0 <= j < len(self) and len(out) < count:
                    out.append(j)
            k += 1
        return out


@pytest.fixture(scope="module")
def cw():
    return parse_prompt_file(resolve_prompt_file("cw"))


@pytest.fixture(scope="module")
def ow_pretrain():
    return parse_prompt_file(resolve_prompt_file("ow_pretrain"))


# ---------------------------------------------------------------------------------------------
# lifting
# ---------------------------------------------------------------------------------------------
def test_point_in_front_takes_the_label_at_its_pixel():
    rig = Rig.nuscenes_like(W, H)
    pts = np.array([[12.0, 1.0, 1.0], [-12.0, 0.5, 1.2], [0.0, 0.0, 60.0]])
    cam_idx, uv = assign_cameras(pts, rig)
    assert CAMERA_NAMES[cam_idx[0]] == "CAM_FRONT" and CAMERA_NAMES[cam_idx[1]] == "CAM_BACK" and cam_idx[2] == -1
    expected_uv, _, ok = rig["CAM_FRONT"].project(pts[:1])
    assert ok[0] and np.allclose(uv[0], expected_uv[0])
    maps = []
    for ci in range(6):
        m = np.full((H, W), 9, np.uint8)
        if CAMERA_NAMES[ci] == "CAM_FRONT":
            u, v = np.floor(uv[0]).astype(int)
            m[v, u] = 4                       # only the pixel under the point says "4"
        maps.append(m)
    maps[CAMERA_NAMES.index("CAM_BACK")][:] = 255  # the back camera sees no label anywhere
    labels = lift_labels(cam_idx, uv, maps)
    assert labels.tolist() == [4, 255, 255]


def test_overlap_goes_to_the_camera_nearest_its_image_centre():
    rig = Rig.nuscenes_like(W, H)
    # CAM_FRONT and CAM_FRONT_LEFT overlap between about 23 and 29 degrees of yaw at 20 m
    for yaw_deg, expected in ((24.0, "CAM_FRONT"), (28.0, "CAM_FRONT_LEFT")):
        yaw = np.deg2rad(yaw_deg)
        p = np.array([[20 * np.cos(yaw), 20 * np.sin(yaw), 1.5]])
        assert rig["CAM_FRONT"].project(p)[2][0] and rig["CAM_FRONT_LEFT"].project(p)[2][0]
        cam_idx, _ = assign_cameras(p, rig)
        assert CAMERA_NAMES[cam_idx[0]] == expected


def test_bilinear_sampling_at_any_stride():
    fmap = np.zeros((2, 3, 4), np.float32)
    fmap[0] = np.arange(4)[None, :]          # channel 0 = column index
    fmap[1] = np.arange(3)[:, None] * 10     # channel 1 = 10 * row index
    # an 80 x 60 image over a 4 x 3 map: cell centres at u = 10, 30, 50, 70 and v = 10, 30, 50
    uv = np.array([[10.0, 10.0], [20.0, 40.0], [70.0, 50.0], [0.0, 0.0], [79.9, 59.9]])
    out = sample_bilinear(fmap, uv, (80, 60))
    assert np.allclose(out, [[0, 0], [0.5, 15], [3, 20], [0, 0], [3, 20]], atol=1e-5)


# ---------------------------------------------------------------------------------------------
# ray casting, voting, feature means
# ---------------------------------------------------------------------------------------------
def test_raycast_frees_only_between_origin_and_hit():
    grid = Grid((0.0, 0.0, 0.0), (10.0, 10.0, 1.0), (1.0, 1.0, 1.0))
    crossed = traverse(np.array([[0.5, 0.5, 0.5]]), np.array([[7.5, 0.5, 0.5]]), grid).reshape(grid.shape)
    assert crossed[:7, 0, 0].all()            # voxels 0..6 before the hit
    assert not crossed[7:, 0, 0].any()        # the hit voxel and the occluded ones behind it
    assert crossed.sum() == 7


def test_raycast_matches_dense_sampling():
    rng = np.random.default_rng(3)
    grid = Grid((-5.0, -5.0, -1.0), (5.0, 5.0, 2.0), (0.5, 0.5, 0.5))
    origin = np.array([0.1, 0.2, 1.3])
    ends = rng.uniform([-8, -8, -1.5], [8, 8, 2.5], size=(150, 3))
    crossed = traverse(origin[None], ends, grid)
    # reference: every voxel touched by a dense sampling of each segment, minus the end voxel
    t = np.linspace(0, 1, 8001)[:, None, None]
    samples = origin + t * (ends - origin)[None]                         # (T, R, 3)
    ref = np.zeros(grid.num_voxels, bool)
    end_idx, _ = grid.points_to_index(ends)
    for r in range(len(ends)):
        idx, inside = grid.points_to_index(samples[:, r])
        idx = idx[inside]
        not_end = ~np.all(idx == end_idx[r], axis=1) | ~grid.points_to_index(ends[r:r + 1])[1][0]
        ref[grid.flat_index(idx[not_end])] = True
    # the two may differ only on voxels a segment grazes (sampling misses corners, DDA stops at the
    # first entry into the end voxel): require near-identity
    assert (crossed != ref).sum() <= 0.01 * ref.sum() + 3
    assert ref.sum() > 80


def test_raycast_default_output_unchanged():
    """traverse without stops gives what it gave before --carve existed (sha256 recorded at commit 4796eb0)."""
    import hashlib

    rng = np.random.default_rng(11)
    grid = Grid((-10.0, -10.0, -1.0), (10.0, 10.0, 2.2), (0.8, 0.8, 0.4))
    origin = np.array([0.3, -0.2, 1.8])
    ends = np.concatenate([rng.uniform([-14, -14, -1.5], [14, 14, 3.0], size=(400, 3)),
                           np.c_[rng.uniform(-9, 9, (200, 2)), rng.uniform(-0.1, 0.1, 200)]])
    crossed = traverse(origin[None], ends, grid)
    assert int(crossed.sum()) == 2769
    assert hashlib.sha256(np.packbits(crossed).tobytes()).hexdigest() == \
        "1169c74f4d230d60b9c592d86b682beabdb74db5f717c43804bcfb68f62cef39"
    assert np.array_equal(traverse(origin[None], ends, grid, t_stop=np.ones(len(ends))), crossed)


# a strip 40 m long, ground layer z index 1 (-0.2..0.2 m) as in Occ3D, LiDAR at 1.7 m (z index 5)
STRIP = Grid((0.0, 0.0, -0.6), (40.0, 0.8, 2.6), (0.8, 0.8, 0.4))
SENSOR = np.array([0.4, 0.4, 1.7])


def carved(ends: np.ndarray, rule: GrazingRule | None, hits: np.ndarray | None = None) -> np.ndarray:
    """(X, Z) voxels the rays SENSOR -> ends carve under `rule` (None: all), the column test over `hits`."""
    stops = None
    if rule is not None:
        stops = grazing_stops(SENSOR, ends, STRIP, rule, occupied_keys(ends if hits is None else hits, STRIP))
    return traverse(SENSOR[None], ends, STRIP, stops).reshape(STRIP.shape)[:, 0, :]


def test_grazing_ray_leaves_the_ground_layer_before_its_hit_uncarved():
    ground_hit = np.array([[36.2, 0.4, 0.0]])                 # x voxel 45, ground layer z 1
    all_rule = carved(ground_hit, None)
    assert all_rule[40:45, 1].all()                            # today: 4 m of ground layer carved before the hit
    grazing = carved(ground_hit, GrazingRule())
    assert not grazing[:, 1].any()                             # the rule: none of it
    assert not grazing[45:, :].any() and not all_rule[45:, :].any()
    # the air higher up along the same ray is still carved, down to half a voxel above the ground layer
    high = all_rule & (np.arange(STRIP.shape[2]) >= 3)[None, :]
    assert high.any() and np.array_equal(grazing & high, high)
    assert grazing.sum() < all_rule.sum()


def test_rays_to_walls_still_carve_the_air_in_front():
    wall = np.stack([np.full(6, 20.2), np.full(6, 0.4), np.arange(6) * 0.4], axis=1)   # 0.0 .. 2.0 m, x voxel 25
    level = np.array([[20.2, 0.4, 1.7]])
    for rule in (None, GrazingRule()):
        c = carved(level, rule, wall)
        assert c[:25, 5].all() and c.sum() == 25               # the level ray: every voxel before the wall
    down = np.array([[20.2, 0.4, 1.2]])                        # a ray descending to the wall's side
    assert np.array_equal(carved(down, GrazingRule(), wall), carved(down, None))
    # without the column test the same ray stops short (its hit is taken for a ground-like surface)
    assert carved(down, GrazingRule(column=False), wall).sum() < carved(down, None).sum()
    # a ray to the wall's base: the ground layer in front of it stays uncarved under the rule, not under all
    base = np.array([[20.2, 0.4, 0.1]])
    assert carved(base, None)[:25, 1].any() and not carved(base, GrazingRule(), wall)[:, 1].any()


def test_vote_majority_per_voxel():
    voxels, labels = vote(np.array([5, 5, 5, 2, 2, 9]), np.array([1, 1, 0, 3, 3, 2]), num_labels=4)
    assert voxels.tolist() == [2, 5, 9] and labels.tolist() == [3, 1, 2]


def test_feature_mean_per_voxel():
    fm = FeatureMean()
    fm.add(np.array([4, 1, 4]), np.array([[1.0, 0.0], [2.0, 2.0], [3.0, 4.0]]))
    fm.add(np.array([1, 7]), np.array([[4.0, 0.0], [5.0, 5.0]]))
    index, mean = fm.result()
    assert index.tolist() == [1, 4, 7]
    assert np.allclose(mean, [[3.0, 1.0], [2.0, 2.0], [5.0, 5.0]])


# ---------------------------------------------------------------------------------------------
# one keyframe end to end on hand-made frames
# ---------------------------------------------------------------------------------------------
def wall_points(x: float, ys, zs) -> np.ndarray:
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    return np.stack([np.full(yy.size, x), yy.ravel(), zz.ravel()], axis=1)


def test_single_frame_labels_free_space_and_occlusion():
    grid = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), (1.0, 1.0, 1.0))
    wall = wall_points(10.3, np.arange(-2.0, 2.01, 0.25), np.arange(0.2, 2.5, 0.25))   # ego frame
    frame = make_frame(ego_to_lidar(wall))
    lifted = lift_frame(frame, ConstantSegmenter({"t0": 3}))
    sample = build_sample(frame, [lifted], num_classes=5, config=PseudoLabelConfig(grid=grid))
    sem = sample.semantics
    i_wall = int(np.floor((10.3 + 20)))
    j0, k1 = 20, 3                           # y in [0, 1), z in [1, 2)
    assert sem[i_wall, j0, k1] == 3           # the wall voxel is labelled by the image
    assert sem[i_wall - 3, j0, k1] == FREE    # between the LiDAR and the wall: free
    assert sem[i_wall + 3, j0, k1] == IGNORE  # behind the wall: unknown, never free
    assert sample.mask_lidar[i_wall - 3, j0, k1] and not sample.mask_lidar[i_wall + 3, j0, k1]
    assert sample.mask_camera[i_wall - 3, j0, k1]           # in front of CAM_FRONT
    from ago_train.pseudo.generate import frustum_mask
    frustum = frustum_mask(grid, frame.rig).reshape(grid.shape)
    assert frustum[i_wall, j0, k1] and not frustum[20, 20, 5]   # ahead of CAM_FRONT / straight above the car
    assert np.array_equal(sample.mask_camera.astype(bool), sample.mask_lidar.astype(bool) & frustum)
    # without ray casting every voxel without a hit is called free
    flat = build_sample(frame, [lifted], 5, PseudoLabelConfig(grid=grid, raycast=False)).semantics
    assert flat[i_wall + 3, j0, k1] == FREE and flat[i_wall, j0, k1] == 3


def test_aggregation_warps_points_with_non_identity_poses():
    grid = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), (0.5, 0.5, 0.5))
    key_pose = pose(30.0, (100.0, 50.0, 0.0))
    other_pose = pose(-20.0, (104.0, 47.0, 0.3))
    p_global = np.array([[108.2, 55.1, 1.1], [96.0, 48.0, 0.7]])
    def to_ego(p, ego2global):
        m = np.linalg.inv(ego2global)
        return p @ m[:3, :3].T + m[:3, 3]
    key = make_frame(ego_to_lidar(to_ego(p_global[:1], key_pose)), key_pose, token="k")
    other = make_frame(ego_to_lidar(to_ego(p_global[1:], other_pose)), other_pose, token="o")
    seg = ConstantSegmenter({"k": 1, "o": 2})
    lifted = [lift_frame(key, seg), lift_frame(other, seg)]
    pts, origin = warp_to(lifted[1], key.ego2global)
    assert np.allclose(pts, to_ego(p_global[1:], key_pose), atol=1e-6)
    assert np.allclose(origin, to_ego((other_pose @ LIDAR2EGO)[:3, 3][None], key_pose)[0], atol=1e-9)
    sem = build_sample(key, lifted, num_classes=3, config=PseudoLabelConfig(grid=grid)).semantics
    for p, label in zip(to_ego(p_global, key_pose), (1, 2)):
        idx, inside = grid.points_to_index(p[None])
        assert inside[0] and sem[tuple(idx[0])] == label


def test_voxel_embeddings_are_point_feature_means():
    grid = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), (1.0, 1.0, 1.0))
    pts = np.array([[10.2, 0.3, 1.2], [10.7, 0.6, 1.5], [10.4, -3.5, 1.4]])   # two in one voxel

    class ColumnEmbedder:   # feature = (u, v) of the image position: bilinear sampling keeps it linear
        name = "uv"
        channels = 2

        def config_dict(self):
            return {}

        def embed(self, frame, camera):
            cam = frame.rig[camera]
            u = (np.arange(cam.width) + 0.5)[None, :].repeat(cam.height, 0)
            v = (np.arange(cam.height) + 0.5)[:, None].repeat(cam.width, 1)
            return np.stack([u, v]).astype(np.float32)

    frame = make_frame(ego_to_lidar(pts))
    lifted = lift_frame(frame, ConstantSegmenter({"t0": 0}), ColumnEmbedder())
    sample = build_sample(frame, [lifted], 1, PseudoLabelConfig(grid=grid))
    uv, _, ok = frame.rig["CAM_FRONT"].project(pts)
    assert ok.all()
    idx, _ = grid.points_to_index(pts)
    flat = grid.flat_index(idx)
    assert sorted(sample.embed_index.tolist()) == sorted(set(flat.tolist()))
    row = dict(zip(sample.embed_index.tolist(), sample.embeds.astype(np.float32)))
    assert np.allclose(row[flat[0]], uv[:2].mean(axis=0), atol=0.1)   # float16 storage
    assert np.allclose(row[flat[2]], uv[2], atol=0.1)


# ---------------------------------------------------------------------------------------------
# file backends
# ---------------------------------------------------------------------------------------------
def test_file_backends_read_the_documented_layout(tmp_path, ow_pretrain):
    frame = make_frame(np.zeros((1, 3)))
    masks = tmp_path / "masks"
    (masks).mkdir()
    (masks / "classes.json").write_text(json.dumps({"1": "car", "2": "driveable surface", "7": "pedestrian"}))
    stem = Path(frame.image_paths["CAM_FRONT"]).stem
    (masks / "CAM_FRONT").mkdir()
    m = np.zeros((H, W), np.uint8)
    m[10:20, 30:40] = 1
    m[50:, :] = 2
    m[0, 0] = 7
    cv2.imwrite(str(masks / "CAM_FRONT" / f"{stem}.png"), m)
    (masks / "CAM_BACK").mkdir()
    np.save(masks / "CAM_BACK" / f"{Path(frame.image_paths['CAM_BACK']).stem}.npy", m)
    seg = FileSegmenter(masks, ow_pretrain)
    out = seg.segment(frame, "CAM_FRONT")
    vehicle, road, ped = (ow_pretrain.index(n) for n in ("vehicle", "driveable_surface", "pedestrian"))
    assert out[15, 35] == vehicle and out[60, 5] == road and out[0, 0] == ped and out[30, 100] == 255
    assert np.array_equal(seg.segment(frame, "CAM_BACK"), out)

    feats = tmp_path / "feats"
    (feats / "CAM_FRONT").mkdir(parents=True)
    np.save(feats / "CAM_FRONT" / f"{stem}.npy", np.ones((8, 5, 9), np.float16))
    emb = FileImageEmbedder(feats, channels=8)
    assert emb.embed(frame, "CAM_FRONT").shape == (8, 5, 9)


def test_file_backends_reject_bad_input(tmp_path, ow_pretrain):
    frame = make_frame(np.zeros((1, 3)))
    stem = Path(frame.image_paths["CAM_FRONT"]).stem
    masks = tmp_path / "masks"
    (masks / "CAM_FRONT").mkdir(parents=True)
    with pytest.raises(AgoInputError, match="classes.json"):
        FileSegmenter(masks, ow_pretrain)
    (masks / "classes.json").write_text(json.dumps({"1": "spaceship"}))
    with pytest.raises(AgoInputError, match="spaceship"):
        FileSegmenter(masks, ow_pretrain)
    (masks / "classes.json").write_text(json.dumps({"1": "car"}))
    seg = FileSegmenter(masks, ow_pretrain)
    with pytest.raises(AgoInputError, match="not found") as e:                       # missing file
        seg.segment(frame, "CAM_FRONT")
    assert stem in str(e.value)
    cv2.imwrite(str(masks / "CAM_FRONT" / f"{stem}.png"), np.zeros((H // 2, W // 2), np.uint8))
    with pytest.raises(AgoInputError, match="80x45 but the image is 160x90") as e:    # wrong size
        seg.segment(frame, "CAM_FRONT")
    assert f"{stem}.png" in str(e.value)
    cv2.imwrite(str(masks / "CAM_FRONT" / f"{stem}.png"), np.full((H, W), 3, np.uint8))
    with pytest.raises(AgoInputError, match="not declared"):                           # undeclared id
        seg.segment(frame, "CAM_FRONT")

    feats = tmp_path / "feats"
    (feats / "CAM_FRONT").mkdir(parents=True)
    emb = FileImageEmbedder(feats, channels=512)
    with pytest.raises(AgoInputError, match="feature map not found"):
        emb.embed(frame, "CAM_FRONT")
    np.save(feats / "CAM_FRONT" / f"{stem}.npy", np.zeros((384, 27, 48), np.float16))
    with pytest.raises(AgoInputError, match="384 channels, expected 512") as e:         # wrong channels
        emb.embed(frame, "CAM_FRONT")
    assert f"{stem}.npy" in str(e.value)

    broken = make_frame(np.ones((4, 3)), ego2global=np.full((4, 4), np.nan))            # pose missing
    with pytest.raises(AgoInputError, match="ego2global"):
        lift_frame(broken, ConstantSegmenter({"t0": 0}))


# ---------------------------------------------------------------------------------------------
# simulated backends
# ---------------------------------------------------------------------------------------------
def synthetic_maps(seed: int = 0, all_classes: bool = False):
    """A hand-made 'rendered' image: sky, manmade, vegetation, road, sidewalk, cars, a truck, bicycles..."""
    rng = np.random.default_rng(seed)
    sem = np.full((H, W), 255, np.uint8)
    sem[30:50, :] = OCC3D_ID["manmade"]
    sem[30:50, 100:] = OCC3D_ID["vegetation"]
    sem[50:, :] = OCC3D_ID["driveable_surface"]
    sem[50:, :30] = OCC3D_ID["sidewalk"]
    sem[50:, 130:] = OCC3D_ID["terrain"]
    for x in range(35, 125, 18):
        sem[44:58, x:x + 12] = OCC3D_ID["car"]
    sem[40:58, 125:140] = OCC3D_ID["truck"]
    sem[52:60, 10:14] = OCC3D_ID["bicycle"]
    sem[52:60, 18:22] = OCC3D_ID["motorcycle"]
    if all_classes:  # a band of blocks with every Occ3D class
        for k in range(NUM_SEMANTIC):
            x0 = k * W // NUM_SEMANTIC
            sem[:28, x0:x0 + W // NUM_SEMANTIC] = k
    depth = np.where(sem == 255, 0.0, 5.0 + 40.0 * rng.random()).astype(np.float32)
    depth[50:] = np.linspace(30, 3, H - 50)[:, None]
    return sem, depth


def sim_frame(token="s0", all_classes=False):
    sem, depth = synthetic_maps(all_classes=all_classes)
    extras = {"semantic": {c: sem for c in CAMERA_NAMES}, "depth": {c: depth for c in CAMERA_NAMES}}
    return make_frame(np.zeros((1, 3)), token=token, extras=extras)


def test_simulated_segmenter_is_deterministic_and_degrades(cw, ow_pretrain):
    frame = sim_frame()
    sem = frame.extras["semantic"]["CAM_FRONT"]
    seg = SimulatedSegmenter(cw)
    a = seg.segment(frame, "CAM_FRONT")
    assert np.array_equal(a, SimulatedSegmenter(cw).segment(frame, "CAM_FRONT"))    # same image, same result
    assert not np.array_equal(a, seg.segment(frame, "CAM_BACK"))                    # other image, other draw
    truth = SimulatedSegmenter(cw, SimSegmenterConfig.perfect()).segment(frame, "CAM_FRONT")
    assert np.array_equal(truth, np.where(sem == 255, 255, sem))                     # cw: class = Occ3D id
    assert (a != truth).mean() > 0.01                                                # degraded
    # ow_pretrain: classes outside the label space become "no label"
    ow_truth = SimulatedSegmenter(ow_pretrain, SimSegmenterConfig.perfect()).segment(frame, "CAM_FRONT")
    assert np.all(ow_truth[sem == OCC3D_ID["manmade"]] == 255)
    assert np.all(ow_truth[sem == OCC3D_ID["truck"]] == ow_pretrain.index("vehicle"))

    def car_to_truck_rate(rate: float) -> float:
        cfg = SimSegmenterConfig(confusion_rate=rate, miss_object=0, miss_surface=0, miss_small=0,
                                 miss_far_per_m=0, boundary_px=0, false_positive_blobs=0)
        s = SimulatedSegmenter(cw, cfg)
        cars = sem == OCC3D_ID["car"]
        hits = [(s.segment(sim_frame(f"s{i}"), "CAM_FRONT")[cars] == OCC3D_ID["truck"]).mean() for i in range(20)]
        return float(np.mean(hits))
    assert car_to_truck_rate(0.0) == 0.0
    assert car_to_truck_rate(0.5) > 0.05
    # missed instances: with a certain miss every object disappears
    miss = SimulatedSegmenter(cw, SimSegmenterConfig(miss_object=1.0, miss_max=1.0, confusion_rate=0, boundary_px=0,
                                                     false_positive_blobs=0, miss_surface=0))
    assert np.all(miss.segment(frame, "CAM_FRONT")[sem == OCC3D_ID["car"]] == 255)
    # boundary errors change pixels near class borders only
    bnd = SimulatedSegmenter(cw, SimSegmenterConfig(boundary_px=30, confusion_rate=0, miss_object=0, miss_surface=0,
                                                    miss_small=0, miss_far_per_m=0, false_positive_blobs=0))
    changed = bnd.segment(frame, "CAM_FRONT") != truth
    assert changed.any()
    border = cv2.dilate((cv2.Laplacian(sem.astype(np.float32), cv2.CV_32F) != 0).astype(np.uint8), np.ones((11, 11)))
    assert np.all(border[changed] > 0)


def _stand_in_text(seed=0, dim=384):
    """Random unit vectors with MiniLM-like pairwise cosines (~0.4) for when no encoder is wanted."""
    rng = np.random.default_rng(seed)
    common = rng.standard_normal(dim)
    common /= np.linalg.norm(common)
    t = 0.64 * common + 0.77 * rng.standard_normal((NUM_SEMANTIC, dim)) / np.sqrt(dim)
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def minilm_class_text():
    from ago_train.pseudo.cli import simulated_text_embeddings
    return simulated_text_embeddings()[0]


@pytest.mark.parametrize("source", ["minilm", "stand-in"])
def test_simulated_embedder_calibration(source):
    text = minilm_class_text() if source == "minilm" else _stand_in_text()
    emb = SimulatedImageEmbedder(text)
    frames = [sim_frame(f"e{i}", all_classes=True) for i in range(3)]
    maps = [emb.embed(f, c) for f in frames for c in CAMERA_NAMES[:2]]
    assert maps[0].shape == (384, 54, 96) and maps[0].dtype == np.float32
    assert np.array_equal(maps[0], emb.embed(frames[0], CAMERA_NAMES[0]))             # deterministic
    stats = similarity_stats(maps, [f.extras["semantic"][c] for f in frames for c in CAMERA_NAMES[:2]], text)
    # documented ranges (docs/vlm_files.md, benchmarks/results/pseudo_labels.md)
    assert 0.28 <= stats["right_cos_mean"] <= 0.42
    assert 0.06 <= stats["gap_mean"] <= 0.14
    assert stats["cos_p95"] <= 0.45
    assert stats["min_class_accuracy"] > 5 * stats["chance"], stats["per_class"]
    assert len(stats["per_class"]) == NUM_SEMANTIC


# ---------------------------------------------------------------------------------------------
# driver: output folder, readers, resumability
# ---------------------------------------------------------------------------------------------
def test_generate_writes_the_contract_and_resumes(tmp_path, cw):
    grid = Grid.with_shape((20, 20, 4))
    wall = wall_points(10.3, np.arange(-3.0, 3.01, 0.3), np.arange(0.2, 2.5, 0.3))
    frames = [make_frame(ego_to_lidar(wall), pose(0, (x, 0, 0)), token=f"tok{i}", extras=sim_frame().extras)
              for i, x in enumerate((0.0, 1.0, 2.0))]
    ds = ListDataset(frames)
    emb = SimulatedImageEmbedder(_stand_in_text(dim=32), SimEmbedderConfig(patch_grid=(9, 16)))
    seg = SimulatedSegmenter(cw)
    cfg = PseudoLabelConfig(grid=grid, num_keyframes=2)
    first = generate(ds, [0, 1, 2], tmp_path / "out", cw, seg, emb, cfg, command="test", progress=False)
    assert first["written"] == 3 and first["skipped"] == 0
    d = PseudoLabelDir(tmp_path / "out")
    assert d.meta["grid"] == grid.to_dict() and d.meta["num_keyframes"] == 2 and d.meta["label_space"]["sha256"] == cw.sha256
    assert d.label_space_path.read_bytes() == Path(cw.source).read_bytes()
    assert d.samples() == [("scene-a", "tok0"), ("scene-a", "tok1"), ("scene-a", "tok2")]
    sem, ml, mc = load_pseudo_labels(tmp_path / "out", "scene-a", "tok1")
    assert sem.shape == grid.shape and sem.dtype == np.uint8 and set(np.unique(sem)) <= set(range(17)) | {FREE, IGNORE}
    assert (sem == FREE).any() and ((sem < 17)).any() and np.all(mc <= ml)
    index, e = load_voxel_embeds(tmp_path / "out", "scene-a", "tok1")
    assert index.dtype == np.int32 and e.dtype == np.float16 and e.shape == (len(index), 32)
    assert np.all(sem.reshape(-1)[index] != FREE)      # embeddings sit on occupied voxels
    before = (tmp_path / "out" / "scene-a" / "tok1" / "labels.npz").stat().st_mtime_ns
    again = generate(ds, [0, 1, 2], tmp_path / "out", cw, seg, emb, cfg, command="again", progress=False)
    assert again["written"] == 0 and again["skipped"] == 3
    assert (tmp_path / "out" / "scene-a" / "tok1" / "labels.npz").stat().st_mtime_ns == before
    with pytest.raises(AgoInputError, match="other settings"):
        generate(ds, [0], tmp_path / "out", cw, seg, emb, PseudoLabelConfig(grid=grid, num_keyframes=3),
                 progress=False)


def test_carve_rule_is_recorded_and_checked_on_resume(tmp_path, cw):
    grid = Grid.with_shape((20, 20, 4))
    wall = wall_points(10.3, np.arange(-3.0, 3.01, 0.3), np.arange(0.2, 2.5, 0.3))
    ds = ListDataset([make_frame(ego_to_lidar(wall), token="tok0", extras=sim_frame().extras)])
    seg = SimulatedSegmenter(cw)
    out = tmp_path / "out"
    generate(ds, [0], out, cw, seg, None, PseudoLabelConfig(grid=grid), progress=False)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["carve"] == "all" and meta["config"]["carve"] is None
    with pytest.raises(AgoInputError, match="carve, config differ"):
        generate(ds, [0], out, cw, seg, None, PseudoLabelConfig(grid=grid, carve=GrazingRule()), progress=False)
    # a folder from before --carve (no carve recorded) resumes as `all`
    del meta["carve"], meta["config"]["carve"]
    (out / "meta.json").write_text(json.dumps(meta))
    assert generate(ds, [0], out, cw, seg, None, PseudoLabelConfig(grid=grid), progress=False)["skipped"] == 1
    graz = tmp_path / "grazing"
    generate(ds, [0], graz, cw, seg, None, PseudoLabelConfig(grid=grid, carve=GrazingRule()), progress=False)
    meta = json.loads((graz / "meta.json").read_text())
    assert meta["carve"] == "grazing" and meta["config"]["carve"] == {"margin": 0.5, "column": True}


def test_cli_refuses_grazing_without_rays(tmp_path):
    from conftest import ago_in_process

    code, err = ago_in_process(["pseudo-labels", "--data", tmp_path, "--out", tmp_path / "p", "--carve", "grazing",
                                "--no-raycast"])
    assert code == 2 and "--carve" in err and "--no-raycast" in err
    assert not (tmp_path / "p").exists()
    # without --carve, --no-raycast is not refused for it (the default grazing rule applies to rays only)
    code, err = ago_in_process(["pseudo-labels", "--data", tmp_path, "--out", tmp_path / "p", "--no-raycast"])
    assert code == 2 and "--carve" not in err


def test_voxel_feature_sums_equal_per_point_sampling():
    from ago_train.pseudo.lift import feature_sums_per_voxel
    rng = np.random.default_rng(0)
    fmap = rng.standard_normal((6, 5, 9)).astype(np.float32)          # (C, h, w)
    uv = rng.uniform([0, 0], [W, H], size=(200, 2))
    flat = rng.integers(0, 12, size=200)
    voxels, sums, counts = feature_sums_per_voxel(flat, uv, np.moveaxis(fmap, 0, -1), (W, H))
    per_point = sample_bilinear(fmap, uv, (W, H))
    fm = FeatureMean()
    fm.add(flat, per_point)
    index, mean = fm.result()
    assert np.array_equal(voxels, index) and np.array_equal(counts, np.bincount(flat)[index])
    assert np.allclose(sums / counts[:, None], mean, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# on an `ago synth` dataset: the CLI (resumable) and the file path a real user takes
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def synth_root(tmp_path_factory):
    from typer.testing import CliRunner
    from ago_runtime.cli import app
    root = tmp_path_factory.mktemp("synth") / "data"
    r = CliRunner().invoke(app, ["synth", "--out", str(root), "--scenes", "1", "--frames", "2",
                                 "--image-size", "96x54", "--grid", "20x20x4"])
    assert r.exit_code == 0, r.output
    return root


def test_cli_pseudo_labels_is_resumable(synth_root, tmp_path):
    from typer.testing import CliRunner
    from ago_runtime.cli import app
    out = tmp_path / "pl"
    args = ["pseudo-labels", "--data", str(synth_root), "--out", str(out), "--prompts", "ow_pretrain",
            "--segmenter", "sim", "--embedder", "sim", "--grid", "20x20x4", "--keyframes", "2", "--split", "all"]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    assert "2 written, 0 already there" in first.output
    d = PseudoLabelDir(out)
    assert len(d.samples()) == 2 and d.meta["embedder"]["channels"] == 384
    assert d.meta["created_by"].startswith("ago ") and d.meta["label_space"]["name"] == "ow_pretrain"
    sem, _, _ = d.labels(*d.samples()[0])
    assert sem.shape == (20, 20, 4) and sem[sem < FREE].max() < 5     # 5 ow_pretrain classes
    stamps = [p.stat().st_mtime_ns for p in sorted(out.glob("*/*/*.npz"))]
    second = CliRunner().invoke(app, args)
    assert second.exit_code == 0 and "0 written, 2 already there" in second.output
    assert [p.stat().st_mtime_ns for p in sorted(out.glob("*/*/*.npz"))] == stamps
    changed = ["--embedder", "none", "--keyframes", "3"]                         # later options win
    other = CliRunner().invoke(app, args + changed)
    assert isinstance(other.exception, AgoInputError) and "other settings" in str(other.exception)


def test_label_map_files_give_the_same_pseudo_labels_as_the_truth(synth_root, tmp_path, cw):
    """Masks written in the documented layout (here: the rendered truth) -> same result as the perfect simulation."""
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_train.pseudo.generate import pseudo_sample
    ds = NuScenesDataset(synth_root, load_images=False)
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "classes.json").write_text(json.dumps({str(i + 1): cw.class_names[i] for i in range(NUM_SEMANTIC)}))
    for i in range(len(ds)):
        f = ds[i]
        for cam in CAMERA_NAMES:
            sem = f.extras["semantic"][cam]
            ids = np.where(sem < NUM_SEMANTIC, sem + 1, 0).astype(np.uint8)      # 0 = no label
            (masks / cam).mkdir(exist_ok=True)
            cv2.imwrite(str(masks / cam / f"{Path(f.image_paths[cam]).stem}.png"), ids)
    cfg = PseudoLabelConfig(grid=Grid.with_shape((20, 20, 4)), num_keyframes=2)
    from_files = pseudo_sample(ds, 0, cw, FileSegmenter(masks, cw), None, cfg)
    from_truth = pseudo_sample(ds, 0, cw, SimulatedSegmenter(cw, SimSegmenterConfig.perfect()), None, cfg)
    assert np.array_equal(from_files.semantics, from_truth.semantics)
    assert (from_files.semantics < FREE).sum() > 20


# ---------------------------------------------------------------------------------------------
# seen-class GT mixed in (VEON's X/Y protocol, ago seen-gt)
# ---------------------------------------------------------------------------------------------
def test_mix_seen_gt_rules_on_a_hand_made_block():
    from ago_train.pseudo.seen_gt import mix_seen_gt
    seen = np.array([True, False, True])                    # classes 0, 2 seen; 1 unseen; free = 17
    pseudo = np.array([[[1, 0, 2, 1, FREE, 255]]], np.uint8)            # (1, 1, 6) coarse voxels
    gt = np.full((2, 2, 12), FREE, np.uint8)                            # factor 2 in every axis
    gt[:, :, 0:2] = 0                      # voxel 0: GT block all class 0 (seen) -> 0 although pseudo says 1
    gt[0, 0, 2] = 2                        # voxel 1: one GT voxel of class 2, pseudo 0 -> 2
    gt[:, :, 4:6] = 1                      # voxel 2: GT only unseen class 1, pseudo says seen 2 -> ignored
    gt[0, 0, 6], gt[1, 1, 6], gt[0, 1, 7] = 0, 2, 2   # voxel 3: two of class 2 beat one of class 0
    gt[0, 0, 10] = 0                       # voxel 5: pseudo unlabelled, GT class 0 there -> 0
    mixed = mix_seen_gt(pseudo, gt, seen)
    assert mixed.tolist() == [[[0, 2, 255, 2, FREE, 0]]]
    assert mix_seen_gt(pseudo, gt, np.zeros(3, bool)).tolist() == pseudo.tolist()   # X = 0: unchanged
    with pytest.raises(ValueError):
        mix_seen_gt(pseudo, gt[:, :, :11], seen)


def test_cli_seen_gt_takes_the_seen_classes_from_gt(synth_root, tmp_path):
    from typer.testing import CliRunner
    from ago_runtime.cli import app
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.formats.occ3d import labels_path, load_semantics
    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
    pl = tmp_path / "pl"
    r = CliRunner().invoke(app, ["pseudo-labels", "--data", str(synth_root), "--out", str(pl), "--prompts", "cw",
                                 "--segmenter", "sim", "--embedder", "sim", "--grid", "20x20x4", "--keyframes", "2",
                                 "--split", "all"])
    assert r.exit_code == 0, r.output
    out = tmp_path / "mixed"
    args = ["seen-gt", "--data", str(synth_root), "--pseudo", str(pl), "--prompts", "veon_9_8", "--out", str(out),
            "--split", "all"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    assert "2 written" in r.output
    space = parse_prompt_file(resolve_prompt_file("veon_9_8"))
    seen = space.known_mask()
    ds = NuScenesDataset(synth_root, load_images=False)
    d, src = PseudoLabelDir(out), PseudoLabelDir(pl)
    assert d.meta["seen_gt"]["seen"] == [c for c, s in zip(space.class_names, seen) if s]
    assert (out / "label_space.txt").is_file() and len(d.samples()) == 2
    lut = space.gt_lut()
    for scene, token in d.samples():
        mixed, _, _ = d.labels(scene, token)
        before, _, _ = src.labels(scene, token)
        gt = lut[load_semantics(labels_path(ds.gts_root, scene, token))[0]]
        gt_seen = (gt < len(seen)) & seen[np.minimum(gt, len(seen) - 1)]
        assert np.array_equal(mixed[gt_seen], gt[gt_seen])                 # same grid here: GT where seen
        labelled_seen = (mixed < len(seen)) & seen[np.minimum(mixed, len(seen) - 1)]
        assert not (labelled_seen & ~gt_seen).any()                         # no seen class without GT
        rest = ~gt_seen & ~((before < len(seen)) & seen[np.minimum(before, len(seen) - 1)])
        assert np.array_equal(mixed[rest], before[rest])                    # unseen / free kept
        assert (d.root / scene / token / "embeds.npz").is_file()
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0 and "0 written, 2 already there" in again.output
    other = CliRunner().invoke(app, [a if a != "veon_9_8" else "veon_13_4" for a in args])
    assert isinstance(other.exception, AgoInputError) and "other seen classes" in str(other.exception)
    wrong = CliRunner().invoke(app, ["seen-gt", "--data", str(synth_root), "--pseudo", str(pl), "--prompts",
                                     "ow_pretrain", "--out", str(tmp_path / "w"), "--split", "all"])
    assert isinstance(wrong.exception, AgoInputError) and "classes" in str(wrong.exception)
    assert not (tmp_path / "w").exists()                                    # checked before anything is written


def test_pseudo_labels_in_worker_processes_are_the_same(tmp_path_factory, tmp_path):
    """--jobs 2 labels scenes in two worker processes: the same files as one process, byte for byte."""
    from typer.testing import CliRunner
    from ago_runtime.cli import app
    root = tmp_path_factory.mktemp("synth2") / "data"
    r = CliRunner().invoke(app, ["synth", "--out", str(root), "--scenes", "3", "--frames", "2",
                                 "--image-size", "96x54", "--grid", "20x20x4", "--val-fraction", "0"])
    assert r.exit_code == 0, r.output
    files = {}
    for jobs in (1, 2):
        out = tmp_path / f"pl{jobs}"
        res = CliRunner().invoke(app, ["pseudo-labels", "--data", str(root), "--out", str(out), "--prompts", "cw",
                                       "--segmenter", "sim", "--embedder", "sim", "--grid", "20x20x4",
                                       "--keyframes", "2", "--split", "all", "--jobs", str(jobs)])
        assert res.exit_code == 0, res.output
        assert "6 written" in res.output
        files[jobs] = {p.relative_to(out): p.read_bytes() for p in sorted(out.glob("*/*/*.npz"))}
    assert len(files[1]) == 12 and files[1] == files[2]     # labels.npz + embeds.npz per sample


def test_moving_keyframe_takes_moving_classes_from_the_keyframe_only(tmp_path, cw):
    """--moving keyframe: a car seen at another place by another keyframe (it moved) is not labelled there, while
    the static points of the other keyframes still are; --moving aggregate (the default) labels both car places.
    The rule is recorded in meta.json; a folder from before --moving resumes as aggregate, and asking for keyframe on
    it is refused."""
    from ago_train.pseudo.generate import moving_classes

    car, manmade = cw.class_names.index("car"), cw.class_names.index("manmade")
    assert car in moving_classes(cw) and manmade not in moving_classes(cw)
    assert cw.class_names.index("driveable_surface") not in moving_classes(cw)
    grid = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), (0.5, 0.5, 0.5))
    here, there, wall = np.array([[8.2, 0.3, 0.7]]), np.array([[8.2, 4.1, 0.7]]), np.array([[12.1, -3.2, 1.3]])
    key = make_frame(ego_to_lidar(here), token="k")
    moved = make_frame(ego_to_lidar(there), token="o")
    static = make_frame(ego_to_lidar(wall), token="s")
    seg = ConstantSegmenter({"k": car, "o": car, "s": manmade})
    lifted = [lift_frame(key, seg), lift_frame(moved, seg), lift_frame(static, seg)]

    def label_at(sem, p):
        idx, inside = grid.points_to_index(p)
        assert inside[0]
        return int(sem[tuple(idx[0])])

    agg = build_sample(key, lifted, len(cw.class_names), PseudoLabelConfig(grid=grid), moving=moving_classes(cw))
    kf = build_sample(key, lifted, len(cw.class_names), PseudoLabelConfig(grid=grid, moving="keyframe"),
                      moving=moving_classes(cw))
    assert [label_at(agg.semantics, p) for p in (here, there, wall)] == [car, car, manmade]
    assert [label_at(kf.semantics, p) for p in (here, wall)] == [car, manmade]
    assert label_at(kf.semantics, there) != car
    with pytest.raises(AgoInputError, match="--moving"):
        PseudoLabelConfig(grid=grid, moving="sweep")

    ds = ListDataset([make_frame(ego_to_lidar(np.concatenate([here, wall])), token="tok0", extras=sim_frame().extras)])
    sim = SimulatedSegmenter(cw)
    out = tmp_path / "out"
    generate(ds, [0], out, cw, sim, None, PseudoLabelConfig(grid=grid), progress=False)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["config"]["moving"] == "aggregate"
    del meta["config"]["moving"]   # a folder from before --moving
    (out / "meta.json").write_text(json.dumps(meta))
    assert generate(ds, [0], out, cw, sim, None, PseudoLabelConfig(grid=grid), progress=False)["skipped"] == 1
    with pytest.raises(AgoInputError, match="config differ"):
        generate(ds, [0], out, cw, sim, None, PseudoLabelConfig(grid=grid, moving="keyframe"), progress=False)


def box_at(centre, yaw_deg: float = 0.0, wlh=(2.0, 4.0, 1.6)) -> tuple[np.ndarray, np.ndarray]:
    m = pose(yaw_deg, centre)
    return m, np.asarray(wlh, float)


def test_follow_tracks_carries_moving_points_along_their_boxes():
    """--moving track's rule: a point in a box that moved goes with the box (a rigid motion: translation and turn);
    a parked box leaves its points where they are; a movable point in no box, or in the box of an object the
    sample does not annotate, is dropped; points not movable are never touched."""
    from ago_train.pseudo.generate import follow_tracks

    then = {"moved": box_at((10.0, 5.0, 0.8), 0.0), "parked": box_at((-6.0, 3.0, 0.8), 30.0),
            "gone": box_at((0.0, -9.0, 0.8))}
    now = {"moved": box_at((14.0, 5.0, 0.8), 90.0), "parked": box_at((-6.0, 3.0, 0.8), 30.0),
           "new": box_at((3.0, 3.0, 0.8))}
    pts = np.array([[11.0, 5.5, 1.0],      # in the moved box, 1 m ahead of its centre, 0.5 m to its left
                    [-6.2, 3.1, 1.2],      # in the parked box
                    [0.3, -9.2, 0.5],      # in the box of an object the sample does not annotate
                    [20.0, 20.0, 1.0],     # in no box
                    [10.5, 5.0, 0.9]])     # in the moved box, but not a moving class (a wall behind it, say)
    movable = np.array([True, True, True, True, False])
    out, dropped = follow_tracks(pts, movable, then, now)
    assert dropped.tolist() == [False, False, True, True, False]
    # the moved box turned 90 degrees left about its centre: 1 m ahead, 0.5 m left -> 0.5 m behind in x, 1 m in y
    assert np.allclose(out[0], [14.0 - 0.5, 5.0 + 1.0, 1.0])
    assert np.allclose(out[1], pts[1]) and np.allclose(out[4], pts[4])
    assert follow_tracks(pts, np.zeros(5, bool), then, now)[1].sum() == 0


def test_moving_track_labels_a_moved_car_at_its_place_in_the_sample(tmp_path, cw):
    """--moving track, end to end through build_sample: another keyframe's car points, seen where the car was then,
    are labelled where its box is at the sample (not where they were seen), while --moving keyframe drops them
    and aggregate labels the old place; a parked car's other views still count; static points are kept; another
    keyframe's non-key sweeps (no boxes at their times: tracks None) lose their car points as with keyframe."""
    from ago_train.pseudo.generate import moving_classes

    car, manmade = cw.class_names.index("car"), cw.class_names.index("manmade")
    grid = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), (0.5, 0.5, 0.5))
    here, there, wall = np.array([[8.2, 0.3, 0.7]]), np.array([[8.2, 4.1, 0.7]]), np.array([[12.1, -3.2, 1.3]])
    parked_other = np.array([[-8.3, 6.2, 0.7]])   # a parked car the sample's keyframe does not see
    key = make_frame(ego_to_lidar(here), token="k")
    moved = make_frame(ego_to_lidar(np.concatenate([there, parked_other])), token="o")
    static = make_frame(ego_to_lidar(wall), token="s")
    seg = ConstantSegmenter({"k": car, "o": car, "s": manmade})
    lifted = [lift_frame(key, seg), lift_frame(moved, seg), lift_frame(static, seg), lift_frame(moved, seg)]
    then = {"a": box_at((8.2, 4.0, 0.8)), "p": box_at((-8.3, 6.0, 0.8))}
    now = {"a": box_at((8.2, 0.2, 0.8)), "p": box_at((-8.3, 6.0, 0.8))}
    tracks = [None, (then, now), ({}, now), None]   # the last: a non-key sweep of the other keyframe

    def label_at(sem, p):
        idx, inside = grid.points_to_index(p)
        assert inside[0]
        return int(sem[tuple(idx[0])])

    config = PseudoLabelConfig(grid=grid, moving="track")
    tr = build_sample(key, lifted, len(cw.class_names), config, moving=moving_classes(cw), tracks=tracks)
    assert [label_at(tr.semantics, p) for p in (here, wall, parked_other)] == [car, manmade, car]
    assert label_at(tr.semantics, there) != car
    moved_to = there + np.array([[0.0, -3.8, 0.0]])   # where the box carried the other keyframe's point
    assert label_at(tr.semantics, moved_to) == car
    assert tr.stats["labelled_points"] == 4   # here, there (carried), wall, the parked car; the sweep's two dropped
    kf = build_sample(key, lifted, len(cw.class_names), PseudoLabelConfig(grid=grid, moving="keyframe"),
                      moving=moving_classes(cw), tracks=tracks)
    assert label_at(kf.semantics, parked_other) != car and kf.stats["labelled_points"] == 2


def test_moving_track_needs_the_box_tables(synth_root, tmp_path):
    """`ago pseudo-labels --moving track` on an `ago synth` dataset (which has sample_annotation) writes
    pseudo-labels recorded as track; on a dataset without the box tables it is refused with one line naming
    --moving, before anything is written."""
    import contextlib
    import io
    import shutil
    from ago_runtime.cli import run
    from ago_runtime.formats.nuscenes import find_version

    args = ["pseudo-labels", "--prompts", "cw", "--segmenter", "sim", "--embedder", "none", "--grid", "20x20x4",
            "--keyframes", "2", "--split", "all", "--moving", "track"]
    out = tmp_path / "pl"
    assert run(args + ["--data", str(synth_root), "--out", str(out)]) == 0
    assert json.loads((out / "meta.json").read_text())["config"]["moving"] == "track"
    assert len(list(out.rglob("labels.npz"))) == 2
    bare = tmp_path / "bare"
    shutil.copytree(synth_root, bare)
    (bare / find_version(bare) / "sample_annotation.json").unlink()
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = run(args + ["--data", str(bare), "--out", str(tmp_path / "pl2")])
    assert code == 2 and "error: --moving: track needs the dataset's box tables" in err.getvalue(), err.getvalue()
    assert not (tmp_path / "pl2").exists()
