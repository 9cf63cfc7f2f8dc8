"""CLI verb `ago metric`: the Occ3D mIoU and RayIoU of predictions against ground truth, and LiDAR measures.

`ago metric --pred DIR --gt DIR [--json out.json] [--md out.md] [--subset NAME=c1,c2]`
    evaluates predictions against Occ3D ground truth (see `ago_runtime.scoring.metric`).
    GT: `<gt>/<scene>/<token>/labels.npz` (searched recursively). Predictions, matched by sample
    token: `<pred>/<scene>/<token>/labels.npz`, `<pred>/<token>/labels.npz` or `<pred>/<token>.npz`,
    each with a `semantics` array at GT resolution or an integer fraction of it (upsampled by
    nearest-neighbour repetition; evaluation is at GT resolution).
`--prompts FILE` scores in that prompt file's label space, as the torch evaluation (`ago eval`) does:
    GT voxels of Occ3D classes no prompt covers are ignored, predictions are matched by class name,
    mIoU is over the file's classes, and its @known line gives "known" / "unknown" subsets.
Both mIoUs are reported (camera mask / every voxel; `--no-mask` picks the per-class table), and RayIoU
(`ago_runtime.scoring.ray_iou`): with `--data DATAROOT` from each frame's scene origins (the LiDAR poses of its
scene's keyframes, as SparseOcc casts), else from one fixed origin (`--ray-origin`) and a note says so.
`--gt` may also be an Occ3D-Waymo folder (`<split>/<scene>/<frame>_04.npz`, e.g. an `ago synth --rig waymo` root):
    tokens are the sample names, mask_camera is `final_voxel_state & infov`, and `--prompts` must be a prompt
    file of `@table: occ3d_waymo` (free, id 23, is scored as the last label).
`--lidar DATAROOT` scores predictions of a dataset's keyframes (nuScenes or Occ3D-Waymo layout) against their own LiDAR
and boxes (`ago_runtime.scoring.lidar_agreement`), beside no-image baselines; `--prior PSEUDO_DIR` adds the
training-frame prior. No Occ3D labels needed.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import numpy as np

import typer

from ago_runtime.errors import AgoInputError
from ago_runtime.readers import open_npz
from ago_runtime.formats.occ3d import load_semantics
from ago_runtime.formats.occ3d_waymo import load_ground_truth
from ago_runtime.scoring.metric import _pct, to_gt_resolution


def find_gt_files(gt_root: Path) -> dict[str, tuple[str, Path]]:
    """sample token -> (scene, GT file) under `gt_root`: Occ3D-nuScenes `<scene>/<token>/labels.npz` (searched
    recursively), else Occ3D-Waymo `<split>/<scene>/<frame>_04.npz` (token = the sample name `<p><scene><frame>`,
    scene = `<split>/<scene>`, as `Occ3DWaymoDataset` names them)."""
    from ago_runtime.formats.occ3d_waymo import SPLITS, list_gt_files, sample_of

    if not gt_root.is_dir():
        raise AgoInputError(gt_root, "ground-truth folder not found")
    out: dict[str, tuple[str, Path]] = {}
    files = sorted(gt_root.rglob("labels.npz"))
    if not files:
        for split in SPLITS:
            if (gt_root / split).is_dir():
                for scene, frame, f in list_gt_files(gt_root, split):
                    out[sample_of(split, scene, frame)] = (f"{split}/{scene:03d}", f)
        if out:
            return out
        raise AgoInputError(gt_root, "no labels.npz found (expected <scene>/<token>/labels.npz, or Occ3D-Waymo's "
                            "<split>/<scene>/<frame>_04.npz)")
    for f in files:
        token = f.parent.name
        if token in out:
            raise AgoInputError(f, f"sample token {token} appears twice (also {out[token][1]})")
        out[token] = (f.parent.parent.name, f)
    return out


def find_prediction_for(pred_root: Path, scene: str, token: str) -> Path | None:
    """The prediction file of a sample token (of a scene), or None."""
    for cand in (pred_root / scene / token / "labels.npz", pred_root / token / "labels.npz",
                 pred_root / f"{token}.npz"):
        if cand.is_file():
            return cand
    return None


def parse_subsets(items: list[str] | None, class_names: list[str]) -> dict[str, list[str]]:
    """`NAME=c1,c2` or `c1,c2` (named by its classes) -> {name: [classes]}; unknown classes refused."""
    out: dict[str, list[str]] = {}
    for item in items or []:
        name, _, rest = item.partition("=") if "=" in item else (item, "", item)
        classes = [c.strip() for c in rest.split(",") if c.strip()]
        bad = [c for c in classes if c not in class_names]
        if not classes or bad:
            raise AgoInputError(None, f"--subset {item!r}: unknown class(es) {bad or '(none given)'}; "
                                      f"known: {', '.join(class_names)}")
        out[name.strip()] = classes
    return out


def prediction_in_space(path: Path, sem: np.ndarray, names: list[str]) -> np.ndarray:
    """A prediction file's labels as indices of `names` (a label space's classes then "free"), matched by
    class name: the file's `bank_semantics` / `bank_class_names` when present (ago infer with a bank
    whose classes are Occ3D classes), else its `semantics` / `class_names`."""
    with open_npz(path, "prediction file") as z:
        if "bank_semantics" in z.files and "bank_class_names" in z.files:
            sem, file_names = np.asarray(z["bank_semantics"]), [str(c) for c in z["bank_class_names"]]
        elif "class_names" in z.files:
            file_names = [str(c) for c in z["class_names"]]
        else:
            raise AgoInputError(path, "--prompts needs prediction files with class names (written by ago infer)")
    index = {c: i for i, c in enumerate(names)}
    lut = np.full(max(len(file_names), 1), 255, np.int64)
    for i, c in enumerate(file_names):
        lut[i] = index.get(c, 255)
    present = np.unique(sem)
    if present.size and present.max() >= len(file_names):
        raise AgoInputError(path, f"labels up to {int(present.max())} but only {len(file_names)} class names")
    outside = [file_names[v] for v in present if lut[v] == 255]
    if outside:
        raise AgoInputError(path, f"predicts {outside[:3]}, not classes of the --prompts file")
    return lut[sem].astype(np.uint8)


def prediction_free_index(path: Path, default: int) -> int:
    """The `free_index` a prediction file states (ago infer writes it), else `default` (Occ3D: 17)."""
    with open_npz(path, "prediction file") as z:
        return int(z["free_index"]) if "free_index" in z.files else default


def parse_origin(text: str) -> tuple[float, float, float]:
    """'x,y,z' metres -> a tuple; anything else is one AgoInputError naming --ray-origin."""
    try:
        xyz = tuple(float(v) for v in text.split(","))
    except ValueError:
        xyz = ()
    if len(xyz) != 3 or not all(np.isfinite(xyz)):
        raise AgoInputError("--ray-origin", f"expected x,y,z in metres like 0.943,0,1.84, got {text!r}")
    from ago_runtime.geometry.grid import Grid

    g = Grid.occ3d()
    if not all(lo <= v < hi for v, lo, hi in zip(xyz, g.range_min, g.range_max)):
        raise AgoInputError("--ray-origin", f"{text!r} lies outside the grid {g.range_min}..{g.range_max}")
    return xyz


def scene_origins_of(data: Path, tokens: list[str]) -> dict[str, np.ndarray]:
    """`--data DATAROOT`: sample token -> RayIoU's ray origins in its ego frame (`ray_iou.scene_origins`: the
    LiDAR positions of its scene's keyframes), from the dataroot's poses (no LiDAR file is read)."""
    from ago_runtime.formats.datasets import dataset_layout, open_dataset
    from ago_runtime.scoring.ray_iou import scene_origins

    if dataset_layout(data) is None:
        raise AgoInputError(data, "--data takes a nuScenes dataroot (v1.0-*/) or an Occ3D-Waymo layout root: "
                            "RayIoU's ray origins come from its LiDAR poses")
    ds = open_dataset(data, load_images=False, load_extras=False)
    index = {t: i for i, t in enumerate(ds.sample_tokens)}
    missing = [t for t in tokens if t not in index]
    if missing:
        raise AgoInputError(data, f"{len(missing)} ground-truth sample token(s) are not keyframes of this dataroot "
                            f"(first: {missing[0]}), so their scenes' poses are unknown")
    members: dict[str, list[int]] = {}
    for i in range(len(ds)):
        members.setdefault(ds.scene_of(i), []).append(i)   # dataset order: time order within a scene
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def pose(i: int):
        if i not in poses:
            poses[i] = ds.lidar_pose(i)
        return poses[i]

    return {t: scene_origins(pose(index[t])[1], [pose(j) for j in members[ds.scene_of(index[t])]]) for t in tokens}


def score_against_gt(pred: Path, gt: Path, space, m_mask, m_all, rays, allow_missing: bool,
                     data: Path | None = None) -> list[str]:
    """Accumulate the Occ3D metric with and without the camera mask, and RayIoU (from the scene origins of
    `data` when given, else from the fixed origin); returns skipped tokens."""
    from ago_runtime.classes import OCC3D_NUSCENES, shipped_name
    from ago_runtime.formats.datasets import gt_folder_class_table
    from ago_runtime.geometry.grid import Grid
    from ago_runtime.progress import track

    gts = find_gt_files(gt)
    pairs, missing = [], []
    for token, (scene, gt_file) in gts.items():
        p = find_prediction_for(pred, scene, token)
        if p is None:
            missing.append(token)
        else:
            pairs.append((token, gt_file, p))
    if missing and not allow_missing:
        raise AgoInputError(pred, f"no prediction for {len(missing)} of {len(gts)} GT frames "
                                  f"(first: {missing[0]}); use --allow-missing to skip them")
    if not pairs:
        raise AgoInputError(pred, "no prediction matches any GT frame")
    origins = None if data is None else scene_origins_of(data, [token for token, _, _ in pairs])
    gt_lut = None if space is None else space.gt_lut(free_index=space.num_classes)
    folder_table = gt_folder_class_table(gt)   # a class_table.json beside the GT, else the files' layout says
    scored_in = space.class_table if space is not None else OCC3D_NUSCENES   # without --prompts: Occ3D-nuScenes ids
    for token, gt_file, p in track(pairs, description="scoring (frames)", total=len(pairs)):
        labels, table = load_ground_truth(gt_file)
        table = folder_table or table
        if table != scored_in:
            use = shipped_name(table) or "<the path of its class_table.json>"
            raise AgoInputError(gt_file, f"holds {table.name} labels, not {scored_in.name} ones: give --prompts with a "
                                f"prompt file of '@table: {use}' (e.g. --prompts waymo/cw_waymo for occ3d_waymo)")
        sem, _ = load_semantics(p)
        gt_sem = labels.semantics
        if space is not None:
            sem = prediction_in_space(p, sem, m_mask.class_names)
            gt_sem = gt_lut[gt_sem]
        sem = to_gt_resolution(sem, labels.shape, p)
        if sem.max() >= m_mask.num_labels:
            raise AgoInputError(p, f"prediction labels must lie in 0..{m_mask.num_labels - 1}, found {sem.max()}")
        m_mask.update(sem, gt_sem, labels.mask_camera.astype(bool))
        m_all.update(sem, gt_sem, None)
        grid = Grid.with_shape(labels.shape)
        rays.update(sem, gt_sem, grid.range_min, grid.voxel_size, None if origins is None else origins[token])
    return missing


def prediction_class_names(path: Path) -> list[str]:
    """The class names a prediction file's `semantics` index: its `class_names` (ago infer writes them), else the
    Occ3D-nuScenes ids."""
    from ago_runtime.classes import OCC3D_CLASSES

    with np.load(path, allow_pickle=False) as z:
        return [str(c) for c in z["class_names"]] if "class_names" in z.files else list(OCC3D_CLASSES)


def load_prior(pseudo: Path, scored: set[str]):
    """`--prior PSEUDO_DIR`: a `TrainingPrior` over every pseudo-label (`<scene>/<token>/labels.npz`) of an
    `ago pseudo-labels` folder (its meta.json gives the classes, the free id and the grid), and the notes to print."""
    from ago_runtime.readers import read_json
    from ago_runtime.scoring.lidar_agreement import TrainingPrior

    meta = read_json(pseudo / "meta.json", missing="--prior: not a pseudo-label folder (no meta.json)")
    try:
        names = [str(c) for c in meta["label_space"]["classes"]]
        shape = tuple(int(v) for v in meta["grid"]["shape"])
        free = int(meta.get("free_index", 17))
    except (KeyError, TypeError, ValueError) as e:
        raise AgoInputError(pseudo / "meta.json", f"--prior: no label_space.classes / grid.shape ({e})") from None
    if len(shape) != 3 or min(shape) < 1 or np.prod(shape) > 2 ** 26:
        raise AgoInputError(pseudo / "meta.json", f"--prior: grid shape {shape} is not a sane (X, Y, Z)")
    files = sorted(pseudo.rglob("labels.npz"))   # <scene>/<token>/ (an Occ3D-Waymo scene is <split>/<scene>)
    if not files:
        raise AgoInputError(pseudo, "--prior: no <scene>/<token>/labels.npz in the pseudo-label folder")
    prior = TrainingPrior(names, free, shape)
    for f in files:
        sem, _ = load_semantics(f)
        if sem.shape != shape:
            raise AgoInputError(f, f"--prior: shape {sem.shape} is not the folder's grid {shape}")
        prior.add(sem)
    seen = sorted(scored & {f.parent.name for f in files})
    notes = [f"the training-frame prior saw {len(seen)} of the scored keyframes' pseudo-labels (it is then no "
             "longer a prior)"] if seen else []
    return prior, notes


def score_against_lidar(pred: Path, dataroot: Path, prior_dir: Path | None, allow_missing: bool):
    """The LiDAR measures (`scoring.lidar_agreement`) of every keyframe of the dataset that has a prediction,
    beside the no-image baselines: (LidarReport, the tokens skipped for lack of a prediction)."""
    from ago_runtime.classes import FREE
    from ago_runtime.errors import AgoNote
    from ago_runtime.formats.datasets import dataset_layout, open_dataset
    from ago_runtime.formats.nuscenes_boxes import (BOX_CLASSES, DatasetBoxes, box_tables_missing, ground_returns,
                                                    return_classes)
    from ago_runtime.geometry.grid import Grid
    from ago_runtime.progress import track
    from ago_runtime.scoring.lidar_agreement import LidarReport, frame_truth, object_volume
    import warnings

    layout = dataset_layout(dataroot)
    if layout is None:
        raise AgoInputError(dataroot, "--lidar takes a nuScenes dataroot (the folder holding v1.0-*/ and samples/) "
                            "or an Occ3D-Waymo layout root (cam_infos.json, kitti_format/<split>/velodyne/)")
    ds = open_dataset(dataroot, load_images=False, load_extras=False)
    if not ds.has_lidar():
        raise AgoInputError(dataroot, "--lidar: the dataset has no LiDAR files")
    pairs, missing = [], []
    for i, token in enumerate(ds.sample_tokens):
        p = find_prediction_for(pred, ds.scene_of(i), token)
        if p is None:
            missing.append(token)
        else:
            pairs.append((i, p))
    if missing and (not allow_missing or not pairs):
        raise AgoInputError(pred, f"no prediction for {len(missing)} of {len(ds)} keyframes of {dataroot} "
                                  f"(first: {missing[0]}); use --allow-missing to skip them")
    notes = []
    boxes = None
    if layout == "nuscenes" and not box_tables_missing(dataroot):
        boxes = DatasetBoxes(dataroot, "--lidar")
    else:
        notes.append("the dataset has no box tables (sample_annotation, instance, category): no return has an object "
                     "class, so object ray IoU is n/a and every return below 0.3 m counts as ground")
    prior, prior_notes = (None, []) if prior_dir is None else load_prior(prior_dir, {ds.sample_tokens[i] for i, _ in pairs})
    notes += prior_notes
    for n in notes:
        warnings.warn(n, AgoNote)
    report = LidarReport(BOX_CLASSES, prior)
    report.notes += notes
    for i, p in track(pairs, description="LiDAR measures (frames)", total=len(pairs)):
        frame = ds[i]
        sem, _ = load_semantics(p)
        free = prediction_free_index(p, FREE)
        grid = Grid.with_shape(sem.shape)
        points = frame.lidar.points_in(frame.ego2global)
        origin = (np.linalg.inv(frame.ego2global) @ frame.lidar.ego2global @ frame.lidar.lidar2ego)[:3, 3]
        if not all(lo <= v < hi for v, lo, hi in zip(origin, grid.range_min, grid.range_max)):
            raise AgoInputError(frame.lidar.path, f"the LiDAR sits at {origin.round(2).tolist()} m, outside the grid")
        frame_boxes = [] if boxes is None else boxes.in_ego(frame.token, frame.ego2global)
        truth = frame_truth(ds.sample_tokens[i], points, origin, grid.shape, grid.range_min, grid.voxel_size,
                            BOX_CLASSES, return_classes(points, frame_boxes), ground_returns(points, frame_boxes))
        try:
            report.update(truth, sem != free, object_volume(sem, prediction_class_names(p), BOX_CLASSES))
        except ValueError as e:
            raise AgoInputError(p if prior is None else prior_dir, str(e)) from None
    return report, missing


def register(app: typer.Typer) -> None:
    @app.command("metric")
    def metric(
        pred: Path = typer.Option(..., "--pred",
                                  help="folder of predictions (<scene>/<token>/labels.npz or <token>.npz)"),
        gt: Optional[Path] = typer.Option(None, "--gt", help="Occ3D ground-truth folder (<scene>/<token>/labels.npz)"),
        lidar: Optional[Path] = typer.Option(
            None, "--lidar", help="nuScenes dataroot: score against each keyframe's own LiDAR and its boxes (object "
            "ray IoU, non-ground / ground ray IoU at 1, 2, 4 m, judged-voxel F1), beside no-image baselines; no "
            "Occ3D labels needed"),
        prior: Optional[Path] = typer.Option(
            None, "--prior", help="with --lidar: a pseudo-label folder of the training keyframes; adds the "
            "training-frame prior baseline (each voxel's most frequent pseudo-label over them)"),
        json_out: Optional[Path] = typer.Option(None, "--json", help="write the summary as JSON"),
        md_out: Optional[Path] = typer.Option(None, "--md", help="write the markdown table"),
        subset: Optional[List[str]] = typer.Option(None, "--subset",
                                                   help="extra mIoU over classes: NAME=c1,c2 (repeatable)"),
        allow_missing: bool = typer.Option(False, "--allow-missing", help="skip GT frames with no prediction"),
        no_mask: bool = typer.Option(False, "--no-mask", help="the main table over every voxel, not only "
                                     "mask_camera (both mIoUs are always reported)"),
        ray_origin: Optional[str] = typer.Option(
            None, "--ray-origin", help="RayIoU without --data: where the query rays start, x,y,z metres in the ego "
            "frame (default: nuScenes LIDAR_TOP, 0.943,0,1.84)"),
        data: Optional[Path] = typer.Option(
            None, "--data", help="with --gt: the dataroot of the GT's keyframes; RayIoU casts from the LiDAR "
            "positions of each frame's scene (SparseOcc's origins) instead of one fixed origin"),
        prompts: Optional[Path] = typer.Option(
            None, "--prompts", help="score in this prompt file's label space (as `ago eval` does): GT voxels of "
            "Occ3D classes no prompt covers are ignored, mIoU over its classes, and known / unknown subsets "
            "from its @known line"),
    ) -> None:
        """Occ3D mIoU (with and without the camera mask) and RayIoU against GT (--gt); LiDAR measures (--lidar)."""
        from ago_runtime.atomic import write_json, write_text
        from ago_runtime.scoring.metric import OccupancyMetric
        from ago_runtime.scoring.ray_iou import RayIoU

        from ago_runtime.outputs import check_distinct_outputs, check_output_file

        if gt is None and lidar is None:
            raise AgoInputError("--gt", "give --gt GT_DIR (Occ3D labels) and/or --lidar DATAROOT (nuScenes LiDAR)")
        if prior is not None and lidar is None:
            raise AgoInputError("--prior", "goes with --lidar DATAROOT (the prior is a LiDAR-measure baseline)")
        if prior is not None and not prior.is_dir():
            raise AgoInputError(prior, "--prior: pseudo-label folder not found")
        if data is not None and ray_origin is not None:
            raise AgoInputError("--ray-origin", "give --ray-origin (one fixed origin) or --data (the scene's LiDAR "
                                "origins), not both")
        if data is not None and gt is None:
            raise AgoInputError("--data", "goes with --gt GT_DIR (RayIoU's ray origins)")
        origin = parse_origin(ray_origin or "0.943,0,1.84")
        space = None
        if prompts is not None:
            from ago_runtime.vocab.prompts import parse_prompt_file

            space = parse_prompt_file(prompts)
            K = space.num_classes
            names, free = list(space.class_names) + ["free"], K
            subsets = parse_subsets(subset, names)
            if space.known and any(c not in space.known for c in space.class_names):
                subsets.setdefault("known", [c for c in space.class_names if c in space.known])
                subsets.setdefault("unknown", [c for c in space.class_names if c not in space.known])
        else:
            from ago_runtime.classes import FREE, OCC3D_CLASSES

            names, free = list(OCC3D_CLASSES), FREE
            subsets = parse_subsets(subset, names)
        m_mask, m_all = OccupancyMetric(names, free_index=free), OccupancyMetric(names, free_index=free)
        rays = RayIoU(names, free, origin=origin)
        for option, target in (("--json", json_out), ("--md", md_out)):
            if target is not None:
                check_output_file(target, option)   # before scoring, not after the table
        check_distinct_outputs(("--json", json_out), ("--md", md_out))
        if not pred.is_dir():
            raise AgoInputError(pred, "prediction folder not found")
        if gt is not None and data is None:
            import warnings

            from ago_runtime.errors import AgoNote

            warnings.warn(f"RayIoU casts from one fixed origin {list(origin)} m (no --data DATAROOT, so no poses): not "
                          "comparable with published RayIoU, which casts from the scene's LiDAR origins", AgoNote)
        missing = (score_against_gt(pred, gt, space, m_mask, m_all, rays, allow_missing, data)
                   if gt is not None else [])
        report, lidar_missing = score_against_lidar(pred, lidar, prior, allow_missing) if lidar is not None else (None, [])
        parts, summary = [], {}
        if gt is not None:
            m = m_all if no_mask else m_mask
            parts.append(m.to_markdown(subsets))
            parts.append(both_mious_markdown(m_mask, m_all, rays))
            summary = m.summary()
            summary["camera_mask"] = not no_mask
            summary["subsets"] = {name: {"classes": cls, "mIoU": _pct(m.miou(cls))}
                                  for name, cls in subsets.items()}
            summary["mIoU_camera_mask"] = _pct(m_mask.miou())
            summary["mIoU_no_camera_mask"] = _pct(m_all.miou())
            summary["geometry_IoU_camera_mask"] = _pct(m_mask.geometry_iou())
            summary["geometry_IoU_no_camera_mask"] = _pct(m_all.geometry_iou())
            summary["ray_iou"] = rays.summary()
            summary["skipped_frames"] = missing
        if lidar is not None:
            parts.append("LiDAR measures (no Occ3D labels; keyframe LiDAR and boxes of " + str(lidar) + ")\n\n"
                         + report.to_markdown())
            summary["lidar"] = {**report.summary(), "dataroot": str(lidar), "skipped_frames": lidar_missing,
                                "prior_dir": None if prior is None else str(prior)}
        table = "\n".join(parts)
        typer.echo(table)
        if missing or lidar_missing:
            typer.echo(f"skipped {len(missing) + len(lidar_missing)} frame(s) with no prediction", err=True)
        if json_out is not None:
            write_json(json_out, summary)
        if md_out is not None:
            write_text(md_out, table)


def both_mious_markdown(m_mask, m_all, rays) -> str:
    """The short table beside the per-class one: mIoU / geometry IoU with and without the camera mask, RayIoU."""
    r = rays.summary()
    rows = [("mIoU, camera mask", _pct(m_mask.miou())), ("mIoU, every voxel (no camera mask)", _pct(m_all.miou())),
            ("geometry IoU, camera mask", _pct(m_mask.geometry_iou())),
            ("geometry IoU, every voxel", _pct(m_all.geometry_iou())), ("**RayIoU** (mean of 1, 2, 4 m)", r["RayIoU"])]
    rows += [(f"RayIoU@{t:g} m", r[f"RayIoU@{t:g}"]) for t in rays.thresholds]
    lines = ["| measure | % |", "|---|---:|"]
    lines += [f"| {name} | {'n/a' if v is None else f'{v:.2f}'} |" for name, v in rows]
    where = (f"from each frame's scene origins (SparseOcc: {r['origins_used']} origins over {r['frames']} frames"
             + (f", {r['origins_outside_grid']} outside the grid skipped" if r["origins_outside_grid"] else "") + ")"
             if r["origins"] != "fixed" else f"from one fixed origin {r['origin_m']} m, not comparable with published RayIoU")
    lines += ["", f"RayIoU over {r['rays_counted']} rays ({r['rays_per_frame']} per origin {where}; those whose GT "
                  "meets an occupied voxel; docs/metric_and_pictures.md)."]
    return "\n".join(lines) + "\n"
