"""Grid-symmetry augmentation (ago_train/augment.py): labels, E_3D indices and projections move together."""

from __future__ import annotations

import numpy as np
import pytest

from ago_runtime.geometry.camera import Rig
from ago_runtime.geometry.grid import Grid
from ago_runtime.geometry.preprocess import Preprocess
from ago_train.augment import AUGMENTATIONS, GridTransform, draw


@pytest.mark.parametrize("t", [GridTransform(True, False), GridTransform(False, True), GridTransform(True, True)])
def test_a_voxel_keeps_its_label_and_its_pixel(t):
    """After the transform, the voxel that holds a label projects to the same pixel (mirrored in u when the
    images are flipped) of the same camera, and volume() / flat_index() agree."""
    grid = Grid.with_shape((20, 20, 4))
    pre = Preprocess(96, 64)
    ego2img = pre.ego2img(Rig.nuscenes_like(192, 128))
    rng = np.random.default_rng(0)
    sem = rng.integers(0, 18, grid.shape).astype(np.uint8)
    new_sem = t.volume(sem)
    idx = rng.choice(grid.num_voxels, 200, replace=False)
    new_idx = t.flat_index(idx, grid.shape)
    assert np.array_equal(new_sem.reshape(-1)[new_idx], sem.reshape(-1)[idx])
    centres = grid.centres().reshape(-1, 3)[idx]
    A = t.ego_matrix()
    new_centres = grid.centres().reshape(-1, 3)[new_idx]
    assert np.allclose(new_centres, centres @ A[:3, :3].T, atol=1e-5)     # the same point, new coordinates
    new_e2i = t.ego2img(ego2img, pre.width)
    hom = np.c_[centres, np.ones(len(centres))]
    new_hom = np.c_[new_centres, np.ones(len(centres))]
    for v in range(6):
        a = hom @ ego2img[v].T.astype(np.float64)
        b = new_hom @ new_e2i[v].T.astype(np.float64)
        front = a[:, 2] > 0.1
        assert np.allclose(b[:, 2], a[:, 2], atol=1e-4)                   # same depth
        u, nu = a[front, 0] / a[front, 2], b[front, 0] / b[front, 2]
        assert np.allclose(nu, pre.width - u if t.flip_y else u, atol=1e-3)
        assert np.allclose(b[front, 1] / b[front, 2], a[front, 1] / a[front, 2], atol=1e-3)


def test_draws_are_seeded_and_cover_the_kinds():
    assert all(draw("none", 0, e, i).identity for e in range(3) for i in range(5))
    flips = [draw("flip", 1, 0, i) for i in range(200)]
    assert not any(t.rot180 for t in flips) and 60 < sum(t.flip_y for t in flips) < 140
    both = {draw("flip+rot180", 1, 0, i) for i in range(200)}
    assert len(both) == 4
    assert draw("flip+rot180", 3, 2, 9) == draw("flip+rot180", 3, 2, 9)
    with pytest.raises(ValueError):
        draw("rotate", 0, 0, 0)
    assert AUGMENTATIONS == ("none", "flip", "flip+rot180")
