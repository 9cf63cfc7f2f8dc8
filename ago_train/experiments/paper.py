"""The paper's tables beside ours: read `paper_tables.json`, print the paper's table under each of ours, and say
in one sentence what agrees and what does not (Occ3D-Waymo, Tab. G and H).

The paper's numbers come from `paper_tables.json` beside this file: the paper's own tables, copied
from its LaTeX source (via shared/paper/paper_tables.md, checked cell by cell; `source_quality`
"paper_source_verified"). `paper_markdown(paper, ours)` prints, under our table `ours`, the paper's table it
is compared with (`PAPER_BESIDE`), labelled with the paper's table number and LaTeX label; Tab. 2 also gets the
paper's per-class cells averaged over this driver's known / unknown split, which differs from the paper's.
Tab. G and H print the paper's AGO row beside each of ours (`paper_ago_rows`), in the same columns, and
`waymo_g_note` / `waymo_h_note` make the sentence from the numbers of the two rows.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ago_runtime.classes import OCC3D_CLASSES, OCC3D_WAYMO

from .collect import SeedMean, fmt, ow_split, separated, waymo_h_classes

PAPER_TABLES = Path(__file__).with_name("paper_tables.json")


def read_paper_tables() -> dict | None:
    """paper_tables.json as a dict, or None when the file is absent."""
    return json.loads(PAPER_TABLES.read_text(encoding="utf-8")) if PAPER_TABLES.is_file() else None

def md_table(header: list[str], rows: list[list]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        lines.append("| " + " | ".join(x if isinstance(x, str) else fmt(x) for x in r) + " |")
    return lines

def _get(row: dict, path: str):
    """row["a"]["b"] for the path "a.b"; None where a key is missing."""
    for key in path.split("."):
        row = row.get(key) if isinstance(row, dict) else None
    return row

def _paper_cell(value, decimals: int = 2) -> str:
    """One paper value as text: floats with `decimals` places, ints and text as they are, True as a check mark,
    False as '' and None as '–'."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "✓" if value else ""
    if isinstance(value, (str, int)):
        return str(value)
    return f"{value:.{decimals}f}"

def _num(path: str, decimals: int = 2):
    """A column that prints the value at `path`."""
    return lambda row: _paper_cell(_get(row, path), decimals)

def _triple(name: str):
    """A column that prints `name`'s known / unknown / mIoU as the paper does (1 decimal)."""
    return lambda row: " / ".join(_paper_cell(_get(row, f"{name}.{k}"), 1) for k in ("known", "unknown", "mIoU"))

def _with_gain(path: str):
    """A column that prints the value at `path` and, where the paper prints one, its gain: '55.18 (+2.08)'."""
    def cell(row: dict) -> str:
        gain = _get(row, f"{path}_gain")
        return _paper_cell(_get(row, path)) + ("" if gain is None else f" (+{gain:.2f})")
    return cell

def _check(path: str):
    """A column that prints a check mark where the paper has one, else 'no'."""
    return lambda row: "✓" if _get(row, path) else "no"

def _regrouped(classes: list[str]):
    """A column with the mean of the paper's per-class IoU over `classes` ('–' if one of them has no value)."""
    def cell(row: dict) -> str:
        vals = [_get(row, f"iou.{c}") for c in classes]
        return "–" if any(v is None for v in vals) else f"{float(np.mean(vals)):.2f}"
    return cell

def paper_columns(key: str) -> list[tuple[str, object]]:
    """The columns (title, row -> text) printed for paper table `key` of paper_tables.json."""
    classes = [c for c in OCC3D_CLASSES if c != "free"]
    if key in ("tab1_closed_world", "supp_b_pseudo_labels"):
        star = [("mIoU*", _num("mIoU_star"))] if key == "tab1_closed_world" else []
        return [("method", _num("method")), ("mIoU", _num("mIoU"))] + star + [(c, _num(f"iou.{c}")) for c in classes]
    if key == "tab2_open_world":
        known, unknown = ow_split()
        return [("stage", _num("stage")), ("method", _num("method")), ("k. mIoU", _num("known_mIoU")),
                ("u. mIoU", _num("unknown_mIoU")), ("mIoU", _num("mIoU")),
                (f"known, our split ({len(known)})", _regrouped(known)),
                (f"unknown, our split ({len(unknown)})", _regrouped(unknown)),
                (f"all ({len(known) + len(unknown)})", _regrouped(known + unknown))]
    if key == "tab3_paradigm":
        return [("paradigm", _num("paradigm")), ("self-supervised mIoU", _num("self_supervised_mIoU")),
                ("O.W. pretraining", _triple("open_world_pretraining")),
                ("O.W. zero-shot", _triple("open_world_zero_shot")), ("O.W. few-shot", _triple("open_world_few_shot"))]
    if key == "tab4_identifier":
        return [("identifier", _check("identifier")), ("criterion", _num("criterion")),
                ("pretraining", _triple("open_world_pretraining")), ("zero-shot", _triple("open_world_zero_shot"))]
    if key == "tab5_components":
        return [("noise prompts", _check("noise_prompts")), ("L_occ", _check("L_occ")),
                ("geometry IoU", _with_gain("IoU")), ("mIoU", _with_gain("mIoU"))]
    if key in ("supp_e_adapter_depth", "supp_d_align_loss"):
        first = ("adapter layers", _num("adapter_layers")) if key == "supp_e_adapter_depth" else \
            ("align loss", _num("align_loss"))
        return [first, ("pretraining", _triple("open_world_pretraining")),
                ("zero-shot", _triple("open_world_zero_shot")), ("few-shot", _triple("open_world_few_shot"))]
    if key == "supp_i_open_world_detailed":
        known, unknown = ow_split()
        return ([("stage", _num("stage")), ("method", _num("method"))]
                + [(c, _num(f"iou.{c}")) for c in ["vehicle", "cycle"] + known + unknown]
                + [("k. mIoU", _num("known_mIoU")), ("u. mIoU", _num("unknown_mIoU")), ("mIoU", _num("mIoU")),
                   (f"known, our split ({len(known)})", _regrouped(known)),
                   (f"unknown, our split ({len(unknown)})", _regrouped(unknown)),
                   (f"all ({len(known) + len(unknown)})", _regrouped(known + unknown))])
    if key == "tabG_waymo_closed_world":
        return ([("method", _num("method")), ("mIoU", _num("mIoU"))]
                + [(c, _num(f"iou.{c}")) for c in OCC3D_WAYMO.names])
    if key == "tabH_waymo_open_world":
        known, unknown = waymo_h_classes()
        return ([("stage", _num("stage")), ("method", _num("method")), ("k. mIoU", _num("known_mIoU")),
                 ("u. mIoU", _num("unknown_mIoU")), ("mIoU", _num("mIoU"))]
                + [(c, _num(f"iou.{c}")) for c in known + unknown])
    raise KeyError(key)


# our table -> the paper's tables printed under it, and what to say about them
PAPER_BESIDE = {
    "tab1": [("tab1_closed_world", ""),
             ("supp_b_pseudo_labels", "The paper's pseudo-labels, beside ours above.")],
    "tab2": [("tab2_open_world", "The paper's k. / u. mIoU average 5 known and 5 unknown classes in pretraining "
                                 "and 3 known (pedestrian, driveable surface, sidewalk) and 12 unknown in the other "
                                 "stages, where car ... motorcycle count as unknown; our split counts them known. "
                                 "The last three columns average the paper's per-class cells over our split.")],
    "tab3": [("tab3_paradigm", "Each open-world cell is known / unknown / mIoU, on the paper's split (see Tab. 2).")],
    "tab4": [("tab4_identifier", "Each cell is known / unknown / mIoU, on the paper's split (see Tab. 2).")],
    "tab5": [("tab5_components", "Gains in brackets are over the row above, as printed.")],
    "tabI": [("supp_i_open_world_detailed", "The paper's rows are its ablations (its full AGO rows are Tab. 2's); "
                                            "k. / u. mIoU on its 3 / 12 split, the last three columns over ours. "
                                            "Pretraining rows score 5 classes (vehicle and cycle, not their "
                                            "refinements).")],
    "supp": [("supp_e_adapter_depth", "Each cell is known / unknown / mIoU, on the paper's split (see Tab. 2)."),
             ("supp_d_align_loss", "")],
    "tabG": [("tabG_waymo_closed_world", "The paper's GO is Occ3D-Waymo's general object, its sidewalk the "
                                         "table's walkable.")],
    "tabH": [("tabH_waymo_open_world", "Pretraining rows score cycle whole (bicycle and motorcycle '–'), the "
                                       "other stages bicycle and motorcycle (cycle '–'), as in our rows.")],
}

def paper_markdown(paper: dict | None, ours: str) -> list[str]:
    """Markdown lines with the paper's tables that go under our table `ours` ([] without paper tables)."""
    if not paper:
        return []
    lines = []
    for key, comment in PAPER_BESIDE[ours]:
        t = paper.get(key)
        if not t:
            continue
        cols = paper_columns(key)
        lines += ["", f"Paper, {t['source']} (the paper's own numbers, from its LaTeX source):", ""]
        lines += md_table([title for title, _ in cols], [[cell(r) for _, cell in cols] for r in t["rows"]])
        if comment:
            lines += ["", comment]
        if t.get("ambiguity"):
            lines += ["", f"In the paper: {t['ambiguity']}."]
        if t.get("consistency"):
            lines += ["", f"Checked against the paper's per-class cells: {t['consistency']}."]
    return lines


# Occ3D-Waymo: each stage of our Tab. G and H beside the paper's AGO row
PAPER_AGO = "AGO (ours)"

WAYMO_STAGES = (("pretraining", "Pretraining"), ("zero-shot", "Zero-shot Evaluation"),
                ("few-shot", "Few-shot Finetuning"))


def paper_ago_rows(paper: dict | None, key: str) -> list[dict]:
    """The paper's AGO rows of paper table `key` ([] without the paper's tables)."""
    return [r for r in ((paper or {}).get(key) or {}).get("rows", []) if r.get("method") == PAPER_AGO]

def _names(classes: list[str]) -> str:
    return ", ".join(classes) or "none"

def waymo_g_note(t: dict) -> list[str]:
    """One sentence on what agrees and what does not between our Tab. G row and the paper's, from their numbers."""
    ours = [r for r in t["rows"] if r["method"].startswith("ago") and r["mIoU"] is not None]
    paper = [r for r in t["rows"] if r.get("paper")]
    if not ours or not paper:
        return []
    a, b = ours[0], paper[0]
    both = [c for c in t["classes"] if a["iou"].get(c) is not None and b["iou"].get(c) is not None]
    high_a = {c for c in both if a["iou"][c] > a["mIoU"]}
    high_b = {c for c in both if b["iou"][c] > b["mIoU"]}
    best_a = max(both, key=lambda c: a["iou"][c]) if both else None
    best_b = max(both, key=lambda c: b["iou"][c]) if both else None
    absent = [c for c in t["classes"] if a["iou"].get(c) is None]
    return ["", f"What agrees and what does not: our mIoU is {float(a['mIoU']):.2f} against the paper's "
                f"{b['mIoU']:.2f} ({float(a['mIoU']) - b['mIoU']:+.2f}); above its own mIoU in both rows: "
                f"{_names([c for c in both if c in high_a & high_b])}; only in ours: "
                f"{_names([c for c in both if c in high_a - high_b])}; only in the paper's: "
                f"{_names([c for c in both if c in high_b - high_a])}; best class: ours {best_a}, the paper's "
                f"{best_b}" + (f"; not in our val GT (no IoU): {_names(absent)}" if absent else "") + "."]

def waymo_h_note(t: dict) -> list[str]:
    """One sentence on what agrees and what does not between our Tab. H stages and the paper's, from the numbers."""
    ours = {r["stage"]: r for r in t["rows"] if not r.get("paper")}
    paper = {r["stage"]: r for r in t["rows"] if r.get("paper")}
    stages = [s for s, _ in WAYMO_STAGES if s in ours and s in paper]
    if not stages:
        return []

    def path(rows: dict, key: str) -> str:
        return " -> ".join("–" if rows[s][key] is None else f"{float(rows[s][key]):.2f}" for s in stages)

    def apart(rows: dict) -> int:
        return sum(1 for s in stages if None not in (rows[s]["known"], rows[s]["unknown"])
                   and rows[s]["known"] > rows[s]["unknown"])

    text = (f"What agrees and what does not ({' -> '.join(stages)}): unknown mIoU ours {path(ours, 'unknown')}, "
            f"the paper's {path(paper, 'unknown')}; known mIoU ours {path(ours, 'known')}, the paper's "
            f"{path(paper, 'known')}; known above unknown in {apart(ours)} of our {len(stages)} stages and in "
            f"{apart(paper)} of the paper's")
    if "zero-shot" in stages and "few-shot" in stages:
        z, f = ours["zero-shot"]["unknown"], ours["few-shot"]["unknown"]
        pz, pf = paper["zero-shot"]["unknown"], paper["few-shot"]["unknown"]
        if None not in (z, f):
            same = (f > z) == (pf > pz)
            spread = ""
            if isinstance(z, SeedMean) and isinstance(f, SeedMean) and min(len(z.values), len(f.values)) > 1:
                spread = ", above the seed spread" if separated(f, z) else ", within the seed spread"
            text += (f"; few-shot fine-tuning {'raises' if f > z else 'does not raise'} our unknown mIoU "
                     f"({float(f) - float(z):+.2f}{spread}), {'as' if same else 'unlike'} the paper's "
                     f"({pf - pz:+.2f})")
    return ["", text + "."]
