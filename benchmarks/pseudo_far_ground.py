"""Far ground in the pseudo-labels: which voxels each ray-casting rule (`ago pseudo-labels --carve`) calls free.

    python -m benchmarks.pseudo_far_ground --data TOWN [--scenes 3] [--work /tmp/pseudo_far_ground] \
        [--reference PSEUDO_DIR] [--out benchmarks/results/pseudo_far_ground.md]

Makes the pseudo-labels of the first --scenes scenes of TOWN's train split (an `ago synth` town with GT) with each
rule, through the verb's own `generate` and the settings of scripts/make_default_bundle.sh (simulated segmenter,
seed 0, 10 keyframes, interval 1, the cpu grid 100x100x16; no embedder: the labels do not depend on it), into
--work (never the repository), and scores them against the GT (Occ3D 200x200x16, mask_camera):

- geometry IoU and mIoU with ago_runtime.scoring.metric.OccupancyMetric, the pseudo-labels upsampled (2, 2, 1)
  and unknown (255) counted as free (benchmarks.learning_curve.pseudo_ceiling); the rules differ only in which
  non-hit voxels are free (17) or unknown (255), so these two numbers cannot tell them apart;
- per range band (horizontal distance of the voxel column from the ego): the share of the GT ground voxels
  (driveable_surface, other_flat, sidewalk, terrain) the pseudo-labels call ground / another class / occupied
  without a label (a hit no mask labelled: 255 inside mask_lidar, what training reads as occupied) / free /
  unknown; the share of the GT-free voxels called free / unknown / occupied (the cost side: free space a rule no
  longer asserts); and of the voxels called free, the share the GT calls occupied (the wrong free labels
  training learns from).

With --reference (a folder `ago pseudo-labels` made of TOWN with those settings before --carve existed, e.g.
scripts/make_default_bundle.sh's), the `all` labels are compared byte for byte with its files of the same keyframes.

Besides the rules, candidates of the grazing rule (raycast.GrazingRule margin / reach) are measured, and two
predictors that look at no image: all free, and the ground slab (every voxel centred below z = 0.2 m driveable
surface: benchmarks.default_bundle_towns.slab_labels).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402

GROUND = ("driveable_surface", "other_flat", "sidewalk", "terrain")
BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 40.0))
GROUND_COLS = ("ground", "other class", "occupied unlabelled", "free", "unknown")
FREE_COLS = ("free", "unknown", "occupied")


def variants():
    """(name, GrazingRule or None, what it is): the two --carve choices first, then candidates of the grazing rule."""
    from ago_train.pseudo.raycast import GrazingRule

    return [("all", None, "`--carve all` (the default before 2026-12-06): every voxel a ray crosses before its hit voxel"),
            ("grazing", GrazingRule(), "`--carve grazing`: stop 0.5 voxel height above the top of the hit's foot "
                                       "(the lowest hit voxel of its column)"),
            ("foot + 0", GrazingRule(margin=0.0), "stop at the top of the foot voxel"),
            ("foot + 1", GrazingRule(margin=1.0), "stop 1 voxel height above the top of the foot voxel"),
            ("hit + 0.5, no column", GrazingRule(margin=0.5, column=False),
             "every descending ray stops 0.5 voxel height above the top of its own hit voxel (walls too)")]


def make(data: Path, out: Path, indices: list[int], rule) -> dict:
    """Pseudo-labels of `indices` with the carving `rule` into `out` (resumable: the verb's generate)."""
    from ago_runtime.formats.datasets import open_dataset
    from ago_train.pseudo.cli import build_backends, parse_grid
    from ago_train.pseudo.generate import PseudoLabelConfig, generate

    space, seg, _ = build_backends("cw", "sim", None, "none", None, 0, data)
    ds = open_dataset(data, load_images=False, load_extras=True)
    config = PseudoLabelConfig(grid=parse_grid("100x100x16"), num_keyframes=10, interval=1, nonkey_sweeps=0,
                               carve=rule)
    return generate(ds, indices, out, space, seg, None, config, command="benchmarks.pseudo_far_ground",
                    progress=False)


def band_of(gt_shape, grid) -> np.ndarray:
    """(X, Y) band index (0..len(BANDS)-1, -1 beyond) of each GT voxel column by its centre's horizontal range."""
    vx = (grid.range_max[0] - grid.range_min[0]) / gt_shape[0]
    vy = (grid.range_max[1] - grid.range_min[1]) / gt_shape[1]
    x = grid.range_min[0] + vx * (np.arange(gt_shape[0]) + 0.5)
    y = grid.range_min[1] + vy * (np.arange(gt_shape[1]) + 0.5)
    r = np.hypot(x[:, None], y[None, :])
    band = np.full(r.shape, -1, np.int64)
    for b, (lo, hi) in enumerate(BANDS):
        band[(r >= lo) & (r < hi)] = b
    return band


class BandCounts:
    """Per band: GT ground voxels by what they are called, GT-free voxels by what they are called, and
    the voxels called free by whether the GT calls them occupied."""

    def __init__(self, ground_idx, free_idx: int):
        self.ground_idx = np.asarray(ground_idx)
        self.free_idx = free_idx
        self.ground = np.zeros((len(BANDS), len(GROUND_COLS)), np.int64)
        self.free = np.zeros((len(BANDS), len(FREE_COLS)), np.int64)
        self.called_free = np.zeros((len(BANDS), 2), np.int64)   # GT free, GT occupied

    def update(self, pred: np.ndarray, hit_unlabelled: np.ndarray, gt: np.ndarray, mask: np.ndarray,
               band: np.ndarray) -> None:
        """pred: label-space indices, free_idx free, 255 unknown; hit_unlabelled: 255 voxels the LiDAR hit; gt: the GT
        in label-space indices (free = free_idx, 255 = a class the space lacks); all at the GT's shape."""
        gt_ground = np.isin(gt, self.ground_idx) & mask
        gt_free = (gt == self.free_idx) & mask
        gt_occ = (gt != self.free_idx) & (gt != 255) & mask
        p_ground = np.isin(pred, self.ground_idx)
        p_free = pred == self.free_idx
        p_unl = (pred == 255) & hit_unlabelled
        p_unknown = (pred == 255) & ~hit_unlabelled
        p_class = ~p_ground & ~p_free & (pred != 255)
        for b in range(len(BANDS)):
            inb = (band == b)[:, :, None]
            g, f = gt_ground & inb, gt_free & inb
            self.ground[b] += [(g & p).sum() for p in (p_ground, p_class, p_unl, p_free, p_unknown)]
            self.free[b] += [(f & p_free).sum(), (f & p_unknown).sum(), (f & (p_class | p_ground | p_unl)).sum()]
            self.called_free[b] += [(p_free & f).sum(), (p_free & gt_occ & inb).sum()]

    def rows(self) -> list[dict]:
        out = []
        for b, (lo, hi) in enumerate(BANDS):
            g, f, c = self.ground[b], self.free[b], self.called_free[b]
            out.append({"band": f"{lo:.0f}-{hi:.0f} m", "gt_ground": int(g.sum()),
                        **{f"ground->{k}": float(v / max(g.sum(), 1)) for k, v in zip(GROUND_COLS, g)},
                        "gt_free": int(f.sum()),
                        **{f"free->{k}": float(v / max(f.sum(), 1)) for k, v in zip(FREE_COLS, f)},
                        "called_free": int(c.sum()), "wrong_free": float(c[1] / max(c.sum(), 1))})
        return out


def score_folder(pseudo: Path, data: Path, split: str) -> dict:
    """Metric (unknown as free) and per-band counts of one pseudo-label folder against the GT."""
    from ago_runtime.formats.datasets import open_dataset
    from ago_runtime.scoring.metric import upsample_nearest
    from ago_train.dataset import PseudoLabelSet

    from benchmarks.learning_curve import pseudo_ceiling

    metric = pseudo_ceiling(str(pseudo), str(data), split)
    p = PseudoLabelSet.open(pseudo)
    ls = p.label_space()
    K = ls.num_classes
    lut = ls.gt_lut(free_index=K).astype(np.uint8)
    counts = BandCounts([ls.class_names.index(n) for n in GROUND], K)
    ds = open_dataset(data, load_images=False, load_extras=False)
    band = None
    for i in ds.split(split):
        scene, token = ds.scene_of(i), ds.sample_tokens[i]
        if not p.has(scene, token):
            continue
        sem = p.labels(scene, token, mark_unlabelled_hits=True)
        gt = ds[i].gt
        factor = tuple(g // s for g, s in zip(gt.semantics.shape, sem.shape))
        up = upsample_nearest(sem, factor)
        band = band_of(gt.semantics.shape, p.grid) if band is None else band
        counts.update(np.where(up == 254, 255, up), up == 254, lut[gt.semantics], gt.mask_camera.astype(bool), band)
    return {"metric": metric, "bands": counts.rows()}


def score_references(data: Path, split: str, scenes: set[str], grid) -> dict:
    """All free and the ground slab on the same GT frames: metric and per-band counts."""
    from ago_runtime.formats.datasets import open_dataset
    from ago_runtime.scoring.metric import OccupancyMetric
    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file

    from benchmarks.default_bundle_towns import slab_labels
    from benchmarks.learning_curve import occupancy_ratio

    ls = parse_prompt_file(resolve_prompt_file("cw"))
    K = ls.num_classes
    lut = ls.gt_lut(free_index=K).astype(np.uint8)
    ds = open_dataset(data, load_images=False, load_extras=False)
    out = {}
    for name in ("all free", "ground slab"):
        m = OccupancyMetric(list(ls.class_names) + ["free"], free_index=K)
        counts = BandCounts([ls.class_names.index(n) for n in GROUND], K)
        band = None
        n = 0
        for i in ds.split(split):
            if ds.scene_of(i) not in scenes:
                continue
            gt = ds[i].gt
            shape = gt.semantics.shape
            vs = [(hi - lo) / s for lo, hi, s in zip(grid.range_min, grid.range_max, shape)]
            pred = (np.full(shape, K, np.uint8) if name == "all free" else
                    slab_labels(shape, grid.range_min, vs, ls.class_names.index("driveable_surface"), K))
            g = lut[gt.semantics]
            mask = gt.mask_camera.astype(bool)
            m.update(pred, g, mask)
            band = band_of(shape, grid) if band is None else band
            counts.update(pred, np.zeros(shape, bool), g, mask, band)
            n += 1
        s = m.summary()
        out[name] = {"metric": {"mIoU": s["mIoU"], "geometry_IoU": s["geometry_IoU"],
                                "occupancy_ratio": occupancy_ratio(s), "frames": n}, "bands": counts.rows()}
    return out


def compare_with_reference(mine: Path, reference: Path) -> str:
    """'N of N keyframes identical' between two pseudo-label folders' labels.npz arrays (mine's keyframes)."""
    from ago_train.pseudo.generate import PseudoLabelDir

    a, b = PseudoLabelDir(mine), PseudoLabelDir(reference)
    samples = a.samples()
    same = sum(all(np.array_equal(x, y) for x, y in zip(a.labels(*st), b.labels(*st))) for st in samples
               if b.has(*st))
    there = sum(b.has(*st) for st in samples)
    return f"{same} of {there} keyframes identical (of {len(samples)} made; {reference})"


def summary_lines(results: dict) -> list[str]:
    """Per band, the GT ground called free and the GT-free called free, `all` beside `grazing`."""
    out = []
    for b, (lo, hi) in enumerate(BANDS):
        a, g = results["all"]["bands"][b], results["grazing"]["bands"][b]
        out.append(f"- {lo:.0f}-{hi:.0f} m: GT ground called free {pct(a['ground->free'])} % (all) -> "
                   f"{pct(g['ground->free'])} % (grazing); GT free called free {pct(a['free->free'])} % -> "
                   f"{pct(g['free->free'])} %; of the voxels called free, GT-occupied {pct(a['wrong_free'])} % -> "
                   f"{pct(g['wrong_free'])} %")
    return out


def pct(x: float) -> str:
    return f"{100 * x:.1f}"


def render(command: str, settings: dict, results: dict, about: dict) -> str:
    lines = ["# Far ground in the pseudo-labels: ray-casting rules (`ago pseudo-labels --carve`)", "",
             "```", command, "```", "",
             f"- commit `{settings['commit']}`; machine shared (load average at the start: {settings['uptime_start']}; "
             f"at the end: {settings['uptime_end']})",
             f"- town `{settings['data']}`, train split, scenes {', '.join(settings['scenes'])} "
             f"({settings['frames']} keyframes); pseudo-labels as scripts/make_default_bundle.sh makes them "
             "(`--segmenter sim --seed 0 --keyframes 10 --interval 1 --grid 100x100x16`, no embedder: the labels "
             "do not depend on it), through `ago_train.pseudo.generate.generate`, written under "
             f"`{settings['work']}`",
             "- scored against the GT (Occ3D 200x200x16, mask_camera): pseudo-labels upsampled (2, 2, 1); "
             "in the metric unknown (255) counts as free (benchmarks.learning_curve.pseudo_ceiling), so geometry IoU "
             "and mIoU cannot differ between rules (they only move voxels between free and unknown); the band "
             "tables show what they do",
             f"- CPU: {settings['cpu']}",
             f"- `all` against the reference folder: {settings['reference']}", "",
             "## Summary: `--carve all` -> `--carve grazing`", ""] + summary_lines(results) + [""]
    lines += ["## Metric (unknown as free) and time", "",
              "| predictor | what | geometry IoU | mIoU | occupancy ratio | seconds to make |", "|---|---|---|---|---|---|"]
    for name, r in results.items():
        m = r["metric"]
        sec = f"{r['seconds']:.1f}" if r.get("seconds") is not None else "-"
        lines.append(f"| {name} | {about.get(name, '')} | {m['geometry_IoU']:.2f} | {m['mIoU']:.2f} | "
                     f"{m['occupancy_ratio']:.2f} | {sec} |")
    lines += ["", "Seconds to make: `generate` wall time for all the keyframes on the shared machine (the first "
              "keyframe, made before timing starts, excluded).", ""]
    lines += ["## GT ground voxels: what each predictor calls them (% per band)", "",
              "| predictor | band | GT ground voxels | " + " | ".join(GROUND_COLS) + " |",
              "|---|---|---|" + "---|" * len(GROUND_COLS)]
    for name, r in results.items():
        for row in r["bands"]:
            lines.append(f"| {name} | {row['band']} | {row['gt_ground']} | "
                         + " | ".join(pct(row[f'ground->{k}']) for k in GROUND_COLS) + " |")
    lines += ["", "## The cost side: GT-free voxels, and the voxels called free (% per band)", "",
              "| predictor | band | GT-free voxels | called free | unknown | occupied | voxels called free | "
              "of them GT-occupied |", "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        for row in r["bands"]:
            lines.append(f"| {name} | {row['band']} | {row['gt_free']} | "
                         + " | ".join(pct(row[f'free->{k}']) for k in FREE_COLS)
                         + f" | {row['called_free']} | {pct(row['wrong_free'])} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--scenes", type=int, default=3, help="the first N scenes of the train split")
    ap.add_argument("--work", type=Path, default=Path("/tmp/pseudo_far_ground"))
    ap.add_argument("--reference", type=Path, help="a pseudo-label folder of TOWN made before --carve: the `all` "
                    "labels must equal its files")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "pseudo_far_ground.md")
    args = ap.parse_args(argv)
    from ago_runtime.formats.datasets import open_dataset
    from ago_train.pseudo.cli import parse_grid

    uptime_start = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    ds = open_dataset(args.data, load_images=False, load_extras=False)
    train = ds.split("train")
    scenes = list(dict.fromkeys(ds.scene_of(i) for i in train))[:args.scenes]
    indices = [i for i in train if ds.scene_of(i) in scenes]
    from benchmarks.machine import cpu_model_and_flags

    results, about = {}, {}
    for name, rule, what in variants():
        folder = args.work / name.replace(" ", "_").replace(",", "").replace(".", "")
        t = time.perf_counter()
        made = make(args.data, folder, indices, rule)
        print(f"{name}: made in {time.perf_counter() - t:.1f} s", flush=True)
        results[name] = {**score_folder(folder, args.data, "train"), "seconds": made["seconds"] if made["written"] else None}
        about[name] = what
    grid = parse_grid("100x100x16")
    refs = score_references(args.data, "train", set(scenes), grid)
    results.update(refs)
    about.update({"all free": "every voxel free (no image)",
                  "ground slab": "every voxel centred below z = 0.2 m driveable surface (no image)"})
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    settings = {"commit": commit + (" (with uncommitted changes)" if dirty else ""), "data": str(args.data),
                "scenes": scenes, "cpu": cpu_model_and_flags()[0],
                "reference": compare_with_reference(args.work / "all", args.reference) if args.reference else "not given", "frames": len(indices), "work": str(args.work), "uptime_start": uptime_start,
                "uptime_end": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()}
    command = "python -m benchmarks.pseudo_far_ground " + " ".join(argv if argv is not None else sys.argv[1:])
    write_text(args.out, render(command, settings, results, about))
    write_text(args.out.with_suffix(".json"), json.dumps({"settings": settings, "results": results}, indent=1))
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    os.environ.setdefault("AGO_NO_PROGRESS", "1")
    main()
