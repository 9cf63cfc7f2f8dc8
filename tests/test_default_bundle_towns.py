"""The per-height geometry breakdown of benchmarks/default_bundle_towns.py (where wrong occupied voxels lie)."""

from pathlib import Path

import numpy as np

from benchmarks.default_bundle_towns import height_table, layer_counts, slab_labels

FREE = 17


def test_layer_counts_per_z_layer_over_the_mask():
    gt = np.full((4, 4, 3), FREE, np.uint8)
    gt[:, :, 0] = 11                       # a ground layer
    pred = gt.copy()
    pred[:, :, 1] = 11                     # the ground doubled one layer up: 16 false positives at z 1
    pred[0, 0, 0] = FREE                   # one ground voxel missed at z 0
    mask = np.ones(gt.shape, bool)
    mask[3, 3, :] = False                  # a column nobody sees
    tp, fp, fn = layer_counts(pred, gt, mask, FREE)
    assert tp.tolist() == [14, 0, 0]
    assert fp.tolist() == [0, 15, 0]
    assert fn.tolist() == [1, 0, 0]


def test_height_table_reports_share_precision_recall_and_skips_empty_layers():
    counts = np.array([[14, 0, 0], [0, 15, 0], [1, 0, 0]])
    rows = height_table(counts, -1.0, 0.4)
    assert len(rows) == 2 + 2              # header + the two layers with anything in them
    assert rows[2].startswith("| 0 | -1.0 .. -0.6 | 100.0 | 100.0 | 93.3 | 0 | 1 |")
    assert rows[3].startswith("| 1 | -0.6 .. -0.2 | 0.0 | 0.0 | n/a | 15 | 0 |")


def test_slab_is_below_its_top_only():
    out = slab_labels((2, 2, 16), np.array([-40.0, -40.0, -1.0]), np.array([0.4, 0.4, 0.4]), 11, FREE)
    assert (out[:, :, :3] == 11).all() and (out[:, :, 3:] == FREE).all()   # centres -0.8, -0.4, 0.0 < 0.2


def test_above_ground_iou_ignores_the_layers_a_slab_covers():
    from benchmarks.default_bundle_towns import above_ground_iou

    # layers centred at -0.8, -0.4, 0.0 (slab) and 0.4, 0.8 (above): only the last two count
    counts = np.array([[50, 50, 50, 3, 1], [0, 0, 9, 1, 1], [0, 0, 9, 2, 0]])
    assert above_ground_iou(counts, -1.0, 0.4) == 100 * 4 / (4 + 2 + 2)
    assert np.isnan(above_ground_iou(np.zeros((3, 5), int), -1.0, 0.4))


def test_free_bias_copy_loads_and_raises_only_the_free_bias(tmp_path):
    """benchmarks.free_bias_sweep's bundle copy: it passes the bundle's own file checks (sha256 updated) and differs
    from the shipped bundle in free_bias alone, by delta."""
    from ago_runtime.predict.bundle import Bundle, resolve_bundle
    from benchmarks.free_bias_sweep import biased_copy

    src = Path(resolve_bundle(None))
    dst = biased_copy(src, tmp_path / "b", 1.5)
    Bundle.load(dst)   # refuses a file whose sha256 differs from bundle.json
    with np.load(src / "heads.npz") as a, np.load(dst / "heads.npz") as b:
        assert a.files == b.files
        for k in a.files:
            if k == "free_bias":
                np.testing.assert_allclose(b[k], a[k] + 1.5)
            else:
                assert np.array_equal(a[k], b[k])
