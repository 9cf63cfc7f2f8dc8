"""The experiments' figures, drawn through ago_runtime.pictures (charts.bar_chart / heatmap, render.voxel_view):

- `entropy_per_class.png`: mean entropy of P (F_3D) and P~ (F~_3D) per GT class, ago zero-shot on ow;
- `modality_gap.png`: cosine of E_3D (simulated VLM, when the data scores have it), F_3D and F~_3D to every
  class text;
- `voxel_renders.png`: val frames' GT, pseudo-labels and the kept predictions of the closed- and open-world runs,
  in the data's class table (`Dataset.class_table`: its ids, its free id and colours; `table_labels` maps a label
  space's ids into it by class name).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.classes import FREE, IGNORE, ClassTable
from ago_runtime.pictures.charts import BLACK, FONT, bar_chart, heatmap

from .collect import views
from .plan import ExperimentProfile, cw_run, ow_run


def figures(out: Path, profile: ExperimentProfile, gap_e3d: dict | None) -> list[str]:
    """Draw the figures whose runs are there into `<out>/figures`; -> the file names written."""
    from ago_runtime.pictures.render import save_png, side_by_side, stack_vertical

    fig_dir = out / "figures"
    made = []
    ow = views(out, ow_run("ago").name)
    if ow and ow.get("stats"):
        s = ow["stats"]
        known = set(s["known"])
        img = bar_chart("Mean entropy per GT class: P (F_3D) vs P~ (adapted F~_3D), ago zero-shot on ow",
                        s["classes"], [("P (F_3D)", s["entropy_main"], (70, 110, 200)),
                                       ("P~ (adapted)", s["entropy_adapted"], (230, 150, 40))],
                        [c not in known for c in s["classes"]], "entropy (nats)")
        save_png(fig_dir / "entropy_per_class.png", img)
        made.append("entropy_per_class.png")
        panels = [("F_3D vs text", heatmap("cosine(F_3D, class text)", s["classes"], s["classes"], np.array(s["cos_main"]))),
                  ("F~_3D vs text", heatmap("cosine(F~_3D, class text)", s["classes"], s["classes"],
                                            np.array(s["cos_adapted"])))]
        if gap_e3d:
            panels.insert(0, ("E_3D (simulated VLM) vs text",
                              heatmap("cosine(E_3D, class text)", gap_e3d["classes"], gap_e3d["classes"],
                                      np.array(gap_e3d["cos"]))))
        save_png(fig_dir / "modality_gap.png", side_by_side(panels))
        made.append("modality_gap.png")
    renders = render_frames(out, profile)
    if renders:
        save_png(fig_dir / "voxel_renders.png", stack_vertical(renders))
        made.append("voxel_renders.png")
    return made


def table_labels(labels: np.ndarray, class_names: list[str], table: ClassTable, free: int | None = None) -> np.ndarray:
    """Label-space ids -> the ids of `table` by class name: `free` (default K = len(class_names), a prediction's;
    pseudo-label files store FREE) -> the table's free id, names the table does not have and any other value ->
    255 (drawn as nothing)."""
    lut = np.full(256, IGNORE, np.uint8)
    names = set(table.names)
    for k, c in enumerate(class_names):
        if c in names:
            lut[k] = table.id_of(c)
    lut[len(class_names) if free is None else free] = table.free_id
    return lut[labels]


def _caption(text: str, width: int) -> np.ndarray:
    img = np.full((28, max(width, 10), 3), 255, np.uint8)
    cv2.putText(img, text, (4, 19), FONT, 0.45, BLACK, 1, cv2.LINE_AA)
    return img


def render_frames(out: Path, profile: ExperimentProfile) -> list[np.ndarray]:
    from ago_runtime.scoring.metric import upsample_nearest
    from ago_runtime.formats.datasets import open_dataset
    from ago_runtime.vocab.prompts import parse_prompt_file
    from ago_runtime.pictures.render import legend, side_by_side, voxel_view
    from ago_runtime.readers import open_npz

    from ..pseudo.generate import load_pseudo_labels

    cw_dir, ow_dir = out / "runs" / cw_run("ago").name / "kept", out / "runs" / ow_run("ago").name / "kept"
    if not cw_dir.is_dir():
        return []
    data = Path(profile.data) if profile.external_data else out / profile.data
    ds = open_dataset(data, load_images=False)
    table = ds.class_table
    ow_names = list(parse_prompt_file("ow").class_names)
    cw_names = list(parse_prompt_file("cw").class_names)
    pseudo_dir = Path(profile.pseudo["cw"]) if profile.external_data else out / profile.pseudo["cw"]
    rows = []
    for f in sorted(cw_dir.glob("cw__*.npz")):
        with open_npz(f, "kept prediction") as z:
            cw_pred, scene, token = z["labels"], str(z["scene"]), str(z["token"])
        gt = ds[ds.index_of(token)].gt
        shape = gt.semantics.shape
        fac = tuple(g // p for g, p in zip(shape, cw_pred.shape))
        mask = gt.mask_camera.astype(bool)
        scale = 1 if shape[0] > 100 else 3

        def view(labels):
            return voxel_view(np.where(mask, labels, table.free_id).astype(np.uint8), scale=scale, crop=False,
                              table=table)

        panels = [("GT", view(gt.semantics))]
        try:
            sem, _ml, _mc = load_pseudo_labels(pseudo_dir, scene, token)
            sem = np.where(sem == IGNORE, FREE, sem)   # never observed: drawn as free
            panels.append(("pseudo-labels", view(upsample_nearest(table_labels(sem, cw_names, table, FREE), fac))))
        except Exception:  # noqa: BLE001 - a frame without pseudo-labels is drawn without that panel
            pass
        panels.append(("ago (cw)", view(upsample_nearest(table_labels(cw_pred, cw_names, table), fac))))
        g = ow_dir / f"ow-min-entropy__{token}.npz"
        if g.is_file():
            with open_npz(g, "kept prediction") as z:
                ow_ids = table_labels(z["labels"], ow_names, table)
            panels.append(("ago zero-shot (ow)", view(upsample_nearest(ow_ids, fac))))
        rows.append(side_by_side(panels))
    if rows:
        rows.insert(0, _caption("Val frames, camera-visible voxels: GT | cw pseudo-labels | ago closed world | "
                                "ago zero-shot on the 15 ow classes (min-entropy)",
                                rows[0].shape[1]))
        rows.append(legend(table.label_names, table.dense_colors(), width=rows[0].shape[1]))
    return rows
