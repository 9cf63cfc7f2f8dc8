"""Build ago_train/experiments/paper_tables.json from the paper's tables in ../shared/paper/paper_tables.md.

paper_tables.md is the paper's tables transcribed from its LaTeX source and checked cell by cell. This
script copies the numbers of the tables the experiments driver compares against into the JSON that
ago_train/experiments/paper.py reads, so that no number is typed by hand. tests/test_paper_tables.py checks the result
against the markdown again, cell by cell.

    python scripts/paper_tables_from_md.py [--md ../shared/paper/paper_tables.md] [--out ago_train/experiments/paper_tables.json]

Each JSON table has `source` (the LaTeX label and table number), `columns` (each markdown header ->
the JSON field or fields its cell fills, dotted paths inside a row) and `rows` (one per markdown row,
in the markdown's order). A cell `a / b / c` fills three fields (known / unknown / mIoU); a cell
`55.18 (+2.08)` fills two (the value and its gain over the row above); `-` and an empty cell give null,
a check mark true and a cross false.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from ago_runtime.atomic import write_text

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MD = REPO.parent / "shared" / "paper" / "paper_tables.md"
DEFAULT_OUT = REPO / "ago_train" / "experiments" / "paper_tables.json"

# Per-class columns: any header in this list fills `iou.<header>`.
CLASS_HEADERS = ("others", "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
                 "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat", "sidewalk", "terrain",
                 "manmade", "vegetation", "vehicle", "cycle")

# Classes as the paper's open-world tables colour them (Table 2 caption; Table I is the same).
OPEN_WORLD_CLASS_GROUPS = {
    "known": ["pedestrian", "driveable_surface", "sidewalk"],
    "known_supercategories": ["vehicle", "cycle"],
    "unknown_refined": ["car", "bus", "construction_vehicle", "trailer", "truck", "bicycle", "motorcycle"],
    "unknown": ["barrier", "traffic_cone", "terrain", "manmade", "vegetation"],
}


def triple(name: str) -> list[str]:
    """The three fields a `known / unknown / mIoU` cell fills, under `name`."""
    return [f"{name}.known", f"{name}.unknown", f"{name}.mIoU"]


OPEN_WORLD_COLUMNS = {"Training Stages": "stage", "Method": "method", "k. mIoU": "known_mIoU",
                      "u. mIoU": "unknown_mIoU", "known mIoU": "known_mIoU", "unknown mIoU": "unknown_mIoU",
                      "mIoU": "mIoU"}

# JSON key -> (LaTeX label, header -> field(s) for the non-class headers, extra fields of the table).
TABLES = {
    "tab1_closed_world": (
        "tab:selfsupervised_benchmark",
        {"Method": "method", "Image Backbone": "image_backbone", "mIoU*": "mIoU_star", "mIoU": "mIoU"},
        {"caption": "Self-supervised 3D occupancy on Occ3D-nuScenes; mIoU* leaves out others and other_flat; "
                    "a dagger marks the authors' retraining"}),
    "tab2_open_world": (
        "tab:open_world_benchmark", OPEN_WORLD_COLUMNS,
        {"caption": "Open world on Occ3D-nuScenes: pretraining on 5 classes, zero-shot evaluation and few-shot "
                    "finetuning on 15; per-class IoU, known (k.) / unknown (u.) / all mIoU",
         "class_groups": OPEN_WORLD_CLASS_GROUPS,
         "ambiguity": "'k.' / 'u.' are not defined in the caption; Table I's headers spell them known / unknown mIoU",
         "consistency": "k. / u. mIoU are the means of the known / unknown columns that have a value (5 / 5 in "
                        "Pretraining; pedestrian, driveable_surface, sidewalk / the other 12 in the other stages) "
                        "and mIoU of all of them, to 0.01 in every row but one: SelfOcc† zero-shot prints k. mIoU "
                        "25.23 where its three cells give 25.32"}),
    "tab3_paradigm": (
        "tab:alignment_ablation",
        {"Training Paradigm": "paradigm", "mIoU: Self.": "self_supervised_mIoU",
         "mIoU: O.W. Pre. (known / unknown / mIoU)": triple("open_world_pretraining"),
         "mIoU: O.W. Z.S. (known / unknown / mIoU)": triple("open_world_zero_shot"),
         "mIoU: O.W. F.S. (known / unknown / mIoU)": triple("open_world_few_shot")},
        {"caption": "Training paradigm: self-supervised mIoU and open-world known / unknown / mIoU in the three "
                    "stages (Align = alignment only, Gro. = grounding)"}),
    "tab4_identifier": (
        "tab:ow_strategy_ablation",
        {"Open World Identifier": "identifier", "Discrimination Criteria": "criterion",
         "Open World: Pretraining mIoU": triple("open_world_pretraining"),
         "Open World: Zero-shot mIoU": triple("open_world_zero_shot")},
        {"caption": "Open-world identifier and its discrimination criterion",
         "ambiguity": "the caption does not define the three values of a cell; read as known / unknown / mIoU "
                      "as in Table 3 (the Min Entropy row equals Table 3's AGO row)"}),
    "tab5_components": (
        "tab:component_ablation",
        {"Method": "method", "Noise Prompts": "noise_prompts", "L_Occ": "L_occ",
         "Self-supervised: IoU": ["IoU", "IoU_gain"], "Self-supervised: mIoU": ["mIoU", "mIoU_gain"]},
        {"caption": "Noise prompts and L_Occ, self-supervised; geometry IoU and mIoU, with the gain over the row "
                    "above as printed; null = no check mark"}),
    "supp_b_pseudo_labels": (
        "tab:pseudo_label_eval",
        {"Method": "method", "Model Base": "model_base", "mIoU": "mIoU"},
        {"caption": "Pseudo-labels on Occ3D-nuScenes: MA = multi-frame aggregation, RC = ray casting, "
                    "GSAM = Grounded SAM; last row: self-supervised AGO"}),
    "supp_c_backbone": (
        "tab:image_bb_ep_reso_ablation",
        {"Method": "method", "Image Backbone": "image_backbone", "Training Epochs": "epochs",
         "Image Resolution": "image_resolution", "Self-supervised IoU": "IoU", "Self-supervised mIoU": "mIoU"},
        {"caption": "Image backbone, training epochs and image resolution, self-supervised",
         "ambiguity": "the ResNet-101 / 24 epochs / 900x1600 row prints mIoU 19.32, where Tables 1, 3, 5, B and F "
                      "give 19.23 for the same model"}),
    "supp_d_align_loss": (
        "tab:align_loss_ablation",
        {"L_Alignment": "align_loss", "Open World: Pretraining mIoU": triple("open_world_pretraining"),
         "Open World: Zero-shot mIoU": triple("open_world_zero_shot"),
         "Open World: Few-shot mIoU": triple("open_world_few_shot")},
        {"caption": "Alignment-loss type (Cosine / MSE / MAE), open world",
         "ambiguity": "the LaTeX caption repeats Table 4's ('inference strategy'); the cells' three values are not "
                      "defined, read as known / unknown / mIoU (the Cosine row equals Table 3's AGO row)"}),
    "supp_e_adapter_depth": (
        "tab:mlp_layer_ablation",
        {"Number of MLP Layers": "adapter_layers", "Open World: Pretraining mIoU": triple("open_world_pretraining"),
         "Open World: Zero-shot mIoU": triple("open_world_zero_shot"),
         "Open World: Few-shot mIoU": triple("open_world_few_shot")},
        {"caption": "Number of MLP layers in the modality adapter, open world",
         "ambiguity": "the cells' three values are not defined in the caption; read as known / unknown / mIoU "
                      "(the 2-layer row equals Table 3's AGO row)"}),
    "supp_f_veon": (
        "tab:veon_comparison",
        {"Method": "method", "Param.": "parameters", "Seen/Unseen mIoU: 0/17": "mIoU_seen0_unseen17",
         "Seen/Unseen mIoU: 9/8": "mIoU_seen9_unseen8", "Seen/Unseen mIoU: 13/4": "mIoU_seen13_unseen4"},
        {"caption": "VEON's open-world benchmark: X seen (with GT) / Y unseen categories"}),
    "supp_i_open_world_detailed": (
        "tab:detailed_open_world_exp", OPEN_WORLD_COLUMNS,
        {"caption": "Per-class open-world results of the ablations of Tables 3 and 4 (the full AGO rows are "
                    "Table 2's); OWI = open world identifier, Max Confi. = max confidence",
         "class_groups": OPEN_WORLD_CLASS_GROUPS,
         "ambiguity": "'OWI' and 'Max Confi.' are not defined in the caption; read from Table 4's rows",
         "consistency": "known / unknown / mIoU are the means of the columns as in Table 2, to 0.01 in every row"}),
}

# Occ3D-Waymo (Tables G and H): the paper's headers -> the class names the driver scores. Tab. G's are the
# Occ3D-Waymo class table's (ago_runtime.classes.OCC3D_WAYMO), Tab. H's the open-world prompt files'
# (prompts/waymo/ow_waymo.txt, ow_waymo_pretrain.txt: they use the paper's own names).
WAYMO_CLOSED_CLASSES = {"GO": "general_object", "vehicle": "vehicle", "bicyclist": "bicyclist",
                        "pedestrian": "pedestrian", "sign": "sign", "traffic light": "traffic_light",
                        "pole": "pole", "construction cone": "construction_cone", "bicycle": "bicycle",
                        "motorcycle": "motorcycle", "building": "building", "vegetation": "vegetation",
                        "tree trunk": "tree_trunk", "road": "road", "sidewalk": "walkable"}
WAYMO_OPEN_CLASSES = ("pedestrian", "road", "sidewalk", "vehicle", "cycle", "bicycle", "motorcycle", "bicyclist",
                      "sign", "traffic light", "pole", "construction cone", "building", "vegetation", "tree trunk")
WAYMO_OPEN_CLASS_GROUPS = {
    "known": ["pedestrian", "road", "sidewalk", "vehicle"],
    "known_supercategories": ["cycle"],
    "unknown_refined": ["bicycle", "motorcycle"],
    "unknown": ["bicyclist", "sign", "traffic light", "pole", "construction cone", "building", "vegetation",
                "tree trunk"],
}
TABLES.update({
    "tabG_waymo_closed_world": (
        "tab:selfsupervised_waymo_benchmark",
        {"Method": "method", "Image Backbone": "image_backbone", "mIoU": "mIoU",
         **{h: f"iou.{c}" for h, c in WAYMO_CLOSED_CLASSES.items()}},
        {"caption": "Self-supervised 3D occupancy on Occ3D-Waymo (15 classes); a dagger marks the authors' "
                    "retraining; per-class keys are the Occ3D-Waymo class table's names (GO = general_object, "
                    "sidewalk = walkable)",
         "ambiguity": "'GO' is not expanded in the paper; read as Occ3D-Waymo's general object",
         "consistency": "mIoU is the mean of the 15 class columns, to 0.01 in every row"}),
    "tabH_waymo_open_world": (
        "tab:open_world_waymo_benchmark",
        {**OPEN_WORLD_COLUMNS, **{h: f"iou.{h}" for h in WAYMO_OPEN_CLASSES}},
        {"caption": "Open world on Occ3D-Waymo: pretraining on pedestrian, road, sidewalk, vehicle and the "
                    "supercategory cycle, zero-shot evaluation and few-shot finetuning on 14 classes (GO "
                    "excluded); per-class IoU, known (k.) / unknown (u.) / all mIoU",
         "class_groups": WAYMO_OPEN_CLASS_GROUPS,
         "consistency": "k. / u. mIoU are the means of the known / unknown columns that have a value (5 / 8 in "
                        "Pretraining; pedestrian, road, sidewalk, vehicle / the other 10 in the other stages) "
                        "and mIoU of all of them, to 0.01 in every row"}),
})

TOP = {
    "source": "the paper's LaTeX source (main paper and supplementary material), via shared/paper/paper_tables.md",
    "source_quality": "paper_source_verified",
    "checked": "paper_tables.md was transcribed from the LaTeX cell by cell and checked twice; this file is "
               "generated from it by scripts/paper_tables_from_md.py and tests/test_paper_tables.py compares "
               "every value with the markdown's cell",
    "units": "IoU and mIoU in %, as printed (2 decimals, or 1 in the known / unknown / mIoU triples)",
    "cells": "'-' in the paper (no value in that stage) and empty cells are null; check mark true, cross false",
    "history": ["Until 2026-12-02 this file held a few numbers copied from a paper summary written by someone "
                "other than the authors; they were replaced by the paper's own tables."],
    "not_included": "Table A (subclass names, text); it is in shared/paper/paper_tables.md",
}


def read_md_tables(text: str) -> dict[str, dict]:
    """Markdown text -> {LaTeX label: {"number": "Table N", "header": [...], "rows": [[cell, ...], ...]}}.

    A table belongs to the nearest `### `tab:...` [Table N]` heading above it; only the first table under
    each heading is read."""
    tables, label, number = {}, None, None
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^### `(tab:[^`]+)` \[(Table [^\]]+)\]", lines[i])
        if m:
            label, number = m.group(1), m.group(2)
        elif lines[i].startswith("|") and label and label not in tables:
            block = []
            while i < len(lines) and lines[i].startswith("|"):
                block.append(lines[i])
                i += 1
            cells = [split_row(ln) for ln in block]
            tables[label] = {"number": number, "header": cells[0], "rows": cells[2:]}
            continue
        i += 1
    return tables


def split_row(line: str) -> list[str]:
    """'| a | b |' -> ['a', 'b'] (cells stripped; empty cells kept as '')."""
    return [c.strip() for c in line.strip().strip("|").split("|")]


def parse_cell(cell: str) -> list:
    """One markdown cell -> its values, in order.

    '-' or '' -> [None]; '✓' -> [True]; '✗' -> [False]; '22.1 / 3.6 / 12.9' -> [22.1, 3.6, 12.9];
    '55.18 (+2.08)' -> [55.18, 2.08]; '24' -> [24]; anything else (a name, '678.1M', '900×1600') -> [text]."""
    if cell in ("-", ""):
        return [None]
    if cell == "✓":
        return [True]
    if cell == "✗":
        return [False]
    if " / " in cell:
        return [number(p) for p in cell.split(" / ")]
    m = re.fullmatch(r"(\S+) \(([+-][0-9.]+)\)", cell)
    if m:
        return [number(m.group(1)), number(m.group(2))]
    try:
        return [number(cell)]
    except ValueError:
        return [cell]


def number(text: str) -> int | float:
    """'24' -> 24, '0.00' -> 0.0, '+2.08' -> 2.08; anything else raises ValueError."""
    if re.fullmatch(r"[+-]?\d+", text):
        return int(text)
    if re.fullmatch(r"[+-]?\d+\.\d+", text):
        return float(text)
    raise ValueError(f"not a number: {text!r}")


def columns_for(header: list[str], named: dict) -> dict[str, list[str]]:
    """Markdown headers -> {header: [field paths]}; class headers go to `iou.<class>`."""
    out = {}
    for h in header:
        if h in named:
            target = named[h]
            out[h] = target if isinstance(target, list) else [target]
        elif h in CLASS_HEADERS:
            out[h] = [f"iou.{h}"]
        else:
            raise ValueError(f"no JSON field for header {h!r}")
    return out


def set_path(row: dict, path: str, value) -> None:
    """row['a']['b'] = value for path 'a.b' (making the inner dicts)."""
    *parents, last = path.split(".")
    for p in parents:
        row = row.setdefault(p, {})
    row[last] = value


def build_table(md_table: dict, label: str, named: dict, extra: dict) -> dict:
    """One parsed markdown table -> its JSON table (source, caption and extras, columns, rows)."""
    columns = columns_for(md_table["header"], named)
    rows = []
    for cells in md_table["rows"]:
        if len(cells) != len(md_table["header"]):
            raise ValueError(f"{label}: row {cells[:2]} has {len(cells)} cells, header {len(md_table['header'])}")
        row: dict = {}
        for h, cell in zip(md_table["header"], cells):
            values = parse_cell(cell)
            paths = columns[h]
            if len(values) > len(paths):
                raise ValueError(f"{label}: cell {cell!r} under {h!r} has more values than fields {paths}")
            values += [None] * (len(paths) - len(values))
            for p, v in zip(paths, values):
                set_path(row, p, v)
        rows.append(row)
    return {"source": f"{label} [{md_table['number']}]", **extra,
            "columns": {h: (p[0] if len(p) == 1 else p) for h, p in columns.items()}, "rows": rows}


def build(md_text: str) -> dict:
    """The whole paper_tables.json content from paper_tables.md's text."""
    md = read_md_tables(md_text)
    out = dict(TOP)
    for key, (label, named, extra) in TABLES.items():
        if label not in md:
            raise ValueError(f"{label} not found in the markdown")
        out[key] = build_table(md[label], label, named, extra)
    return out


def to_text(data: dict) -> str:
    """The JSON text: indented like json.dumps(indent=2), but each table row on one line."""
    rows, placeholder = {}, "@@row{}@@"
    shallow = {}
    for key, value in data.items():
        if isinstance(value, dict) and "rows" in value:
            value = dict(value)
            keys = []
            for row in value["rows"]:
                keys.append(placeholder.format(len(rows)))
                rows[keys[-1]] = row
            value["rows"] = keys
        shallow[key] = value
    text = json.dumps(shallow, indent=2, ensure_ascii=False)
    for key, row in rows.items():
        text = text.replace(json.dumps(key), json.dumps(row, ensure_ascii=False))
    return text + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--md", type=Path, default=DEFAULT_MD)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    data = build(args.md.read_text(encoding="utf-8"))
    write_text(args.out, to_text(data))
    n = sum(len(t["rows"]) for t in data.values() if isinstance(t, dict) and "rows" in t)
    print(f"wrote {args.out}: {len(TABLES)} tables, {n} rows")
    return 0


if __name__ == "__main__":
    sys.exit(main())
