"""Tables (markdown + JSON) and figures from an experiments folder (see driver.py for its layout).

`write_report(out, profile)` reads every `runs/<name>/views.json` that exists, builds the tables whose
runs are there (a table with missing runs says which), draws the figures, and writes
`<out>/results.json`, `<out>/results.md` and `<out>/figures/*.png`. It trains nothing.

The paper's numbers come from `paper_tables.json` beside this file: the paper's own tables, copied
from its LaTeX source (via shared/paper/paper_tables.md, checked cell by cell; `source_quality`
"paper_source_verified"). Under each measured table the markdown prints the paper's table it is
compared with, labelled with the paper's table number and LaTeX label. Tab. 2 also gets the paper's
per-class cells averaged over this driver's known / unknown split, which differs from the paper's.
Tab. G and H (Occ3D-Waymo) print the paper's AGO row beside each of ours, in the same columns, and one
sentence on what agrees and what does not, made from the numbers of the two rows.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_json, write_text
from ago_runtime.classes import OCC3D_CLASSES, OCC3D_WAYMO
from ago_runtime.readers import read_json

from .plan import (ADAPTED_SCALES, FEWSHOT_VARIANTS, PARADIGMS, PROMPTS, WAYMO_PRETRAIN_EVAL, ExperimentProfile,
                   cw_run, fewshot_run, ow_run, seeded, shipped_prompts, waymo_run)

PAPER_TABLES = Path(__file__).with_name("paper_tables.json")
PAPER_NAMES = {"align": "POP-3D-like align", "grounding": "grounding only", "grounding+align": "grounding + align",
               "ago": "AGO (adaptive grounding)", "closed": "closed-world classifier (SelfOcc-like)"}


class SeedMean(float):
    """A mean over training seeds that keeps each seed's value; printed as 'mean (a, b)'."""

    values: list

    def __new__(cls, values):
        obj = super().__new__(cls, float(np.mean(values)))
        obj.values = [float(v) for v in values]
        return obj


def _merge(items: list):
    """Several seeds' views.json trees -> one tree whose numbers are SeedMeans (lists and text: seed 0's)."""
    first = items[0]
    if isinstance(first, dict):
        return {k: _merge([it[k] for it in items if isinstance(it, dict) and k in it]) for k in first}
    if isinstance(first, (int, float)) and not isinstance(first, bool):
        vals = [x for x in items if isinstance(x, (int, float)) and not isinstance(x, bool)]
        return SeedMean(vals) if len(items) > 1 else first
    return first


def _views_of(out: Path, names: list[str], missing: list | None = None) -> dict | None:
    """The views.json of the runs `names` (one per seed) merged into means; absent runs go to `missing`."""
    got = []
    for name in names:
        p = out / "runs" / name / "views.json"
        if p.is_file():
            got.append(read_json(p))
        elif missing is not None:
            missing.append(name)
    return _merge(got) if got else None


def _views(out: Path, name: str, seeds=(0,), missing: list | None = None) -> dict | None:
    return _views_of(out, [seeded(name, s) for s in seeds], missing)


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, SeedMean) and len(v.values) > 1:
        return f"{v:.2f} ({', '.join(f'{x:.2f}' for x in v.values)})"
    return f"{v:.2f}"


def _plain(v):
    """A seed mean printed without its seed values (the per-class columns)."""
    return None if v is None else float(v)


def _row(view: dict | None) -> dict:
    if view is None:
        return {"known": None, "unknown": None, "all": None}
    sub = view.get("subsets") or {}
    return {"known": sub.get("known"), "unknown": sub.get("unknown"), "all": view["mIoU"]}


def _separated(a, b) -> bool:
    """True when two seed means' ranges of values do not overlap (the difference is above the seed spread)."""
    return min(a.values) > max(b.values) or max(a.values) < min(b.values)


def spread_note(rows: list[dict], key: str, label, ref: dict, what: str) -> list[str]:
    """One sentence: which rows differ from `ref` in `key` by more than the seed spread (ranges apart)."""
    r0 = ref.get(key)
    if not isinstance(r0, SeedMean) or len(r0.values) < 2:
        return []
    above, within = [], []
    for r in rows:
        v = r.get(key)
        if r is ref or not isinstance(v, SeedMean) or len(v.values) < 2:
            continue
        (above if _separated(v, r0) else within).append(f"{label(r)} {v - r0:+.2f}")
    if not above and not within:
        return []
    return ["", f"Seed spread ({what}, against {label(ref)}): above the spread (the seeds' ranges do not "
                f"overlap): {'; '.join(above) or 'none'}. Within the spread: {'; '.join(within) or 'none'}."]


def _per_seed(tables: dict) -> dict:
    """results.json keeps every seed's value: rows gain 'per_seed' {key: [values]} for their seed means."""
    for t in tables.values():
        if not isinstance(t, dict):
            continue
        for rows in (t.get("rows"), t.get("depth"), t.get("loss")):
            for r in rows or []:
                ps = {k: v.values for k, v in r.items() if isinstance(v, SeedMean) and len(v.values) > 1}
                if ps:
                    r["per_seed"] = ps
    return tables


# ---------------------------------------------------------------------------------------------
# every number below is the mean over the profile's seeds (a SeedMean that keeps each seed's value)
def table1(out: Path, pseudo_score: dict | None, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 1 — closed world, self-supervised (cw label space, val split)", "rows": [], "missing": []}
    v = _views(out, cw_run("ago").name, profile.seeds, t["missing"])
    if v is None:
        return t
    view = v["views"]["cw"]
    t["rows"].append({"method": "ago (F_3D, no identifier)", "mIoU": view["mIoU"], "mIoU_star": view["mIoU_star"],
                      "geometry_IoU": view["geometry_IoU"], "iou": view["metric"]["iou"]})
    if "cw-min-entropy" in v["views"]:
        w = v["views"]["cw-min-entropy"]
        t["rows"].append({"method": "ago + min-entropy identifier", "mIoU": w["mIoU"], "mIoU_star": w["mIoU_star"],
                          "geometry_IoU": w["geometry_IoU"], "iou": w["metric"]["iou"]})
    if pseudo_score:
        t["rows"].append({"method": "pseudo-labels themselves (val frames)", **pseudo_score})
    return t


def table2(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 2 — open world: pretrain on 5 classes, zero-shot and few-shot on 15 "
                  f"(known / unknown / all mIoU; few-shot k={profile.k}; mean of seeds {list(profile.seeds)})",
         "rows": [], "missing": []}
    cl = _views(out, ow_run("grounding").name, profile.seeds)
    if cl and "ow-closed" in cl["views"]:
        t["rows"].append({"method": PAPER_NAMES["closed"], "stage": "zero-shot", **_row(cl["views"]["ow-closed"])})
    for variant in FEWSHOT_VARIANTS:
        view = "ow-min-entropy" if variant == "ago" else "ow-none"
        v = _views(out, ow_run(variant).name, profile.seeds, t["missing"])
        if v is not None:
            t["rows"].append({"method": PAPER_NAMES[variant], "stage": "zero-shot", **_row(v["views"][view])})
        f = _views_of(out, [fewshot_run(variant, s).name for s in profile.seeds], t["missing"])
        if f is not None:
            t["rows"].append({"method": PAPER_NAMES[variant], "stage": f"{profile.k}-shot", **_row(f["views"][view])})
    return t


def table3(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 3 — training paradigm: self-supervised (cw mIoU) and open world (zero-shot, known / "
                  "unknown / all)", "rows": [], "missing": []}
    for variant in PARADIGMS:
        cw = _views(out, cw_run(variant).name, profile.seeds, t["missing"])
        ow = _views(out, ow_run(variant).name, profile.seeds, t["missing"])
        ow_view = "ow-min-entropy" if variant == "ago" else "ow-none"
        t["rows"].append({"paradigm": PAPER_NAMES[variant],
                          "cw_mIoU": cw["views"]["cw"]["mIoU"] if cw else None,
                          "cw_geometry_IoU": cw["views"]["cw"]["geometry_IoU"] if cw else None,
                          **{f"ow_{k}": x for k, x in _row(ow["views"][ow_view] if ow else None).items()}})
    return t


def table4(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 4 — open-world identifier (ago; known / unknown / all mIoU)", "rows": [], "missing": []}
    zs = _views(out, ow_run("ago").name, profile.seeds, t["missing"])
    fs = _views_of(out, [fewshot_run("ago", s).name for s in profile.seeds], t["missing"])
    names = {"ow-none": "none (F_3D only)", "ow-max-conf": "max confidence", "ow-min-entropy": "min entropy (AGO)",
             "ow-adapted": "adapted F~_3D only"}
    names.update({f"ow-min-entropy-x{s:g}": f"min entropy, adapted logits x{s:g} (diagnostic, chosen on val)"
                  for s in ADAPTED_SCALES})
    for key, label in names.items():
        if zs and key not in zs["views"]:
            continue
        row = {"identifier": label}
        if zs:
            row.update({f"zs_{k}": x for k, x in _row(zs["views"].get(key)).items()})
        if fs:
            row.update({f"fs_{k}": x for k, x in _row(fs["views"].get(key)).items()})
        t["rows"].append(row)
    return t


def table5(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 5 — components (closed world): noise prompts and L_occ", "rows": [], "missing": []}
    for noise, occ in ((False, False), (True, False), (False, True), (True, True)):
        loss = {}
        if not noise:
            loss["use_noise"] = False
        if not occ:
            loss["use_occ"] = False
        v = _views(out, cw_run("ago", **loss).name, profile.seeds, t["missing"])
        view = v["views"]["cw"] if v else None
        t["rows"].append({"noise_prompts": noise, "L_occ": occ, "geometry_IoU": view["geometry_IoU"] if view else None,
                          "mIoU": view["mIoU"] if view else None})
    return t


def table_supp(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Supplementary — adapter depth and alignment loss (ago, open world zero-shot, min-entropy)",
         "depth": [], "loss": [], "missing": []}

    def row(spec) -> dict:
        v = _views(out, spec.name, profile.seeds, t["missing"])
        if v is None:
            return {**_row(None), "unknown_adapted_only": None}
        return {**_row(v["views"]["ow-min-entropy"]),
                "unknown_adapted_only": (v["views"]["ow-adapted"]["subsets"] or {}).get("unknown")}

    t["depth"] = [{"adapter_layers": d, **row(ow_run("ago", adapter_depth=d))} for d in (1, 2, 3, 4)]
    t["loss"] = [{"align_loss": a, **row(ow_run("ago", align_loss=a))} for a in ("cosine", "mse", "l1")]
    t["missing"] = sorted(set(t["missing"]))   # depth 2 and cosine are the same runs
    return t


# Tab. I of the paper's supplement: per-class IoU of the open-world runs. Our method -> (view, paper's name)
TAB_I_METHODS = {"align": [("ow-none", "Align")], "grounding": [("ow-none", "Gro.")],
                 "grounding+align": [("ow-none", "Gro. + Align")],
                 "ago": [("ow-none", "AGO w/o OWI"), ("ow-max-conf", "AGO w/ Max Confi."), ("ow-min-entropy", "AGO (Tab. 2)")]}
TAB_I_AGO_VIEWS = {"ow-none": "AGO, no identifier (F_3D)", "ow-max-conf": "AGO, max confidence",
                   "ow-min-entropy": "AGO, min entropy"}


def table_i(out: Path, profile: ExperimentProfile) -> dict:
    """Per-class IoU over the 15 open-world classes, zero-shot and few-shot, for every paradigm and identifier."""
    t = {"title": "Tab. I — detailed open-world results: per-class IoU on the 15 ow classes (mean of seeds "
                  f"{list(profile.seeds)})", "rows": [], "missing": []}
    stages = [("zero-shot", lambda v: _views(out, ow_run(v).name, profile.seeds, t["missing"]), PARADIGMS),
              (f"{profile.k}-shot", lambda v: _views_of(out, [fewshot_run(v, s).name for s in profile.seeds],
                                                         t["missing"]), FEWSHOT_VARIANTS)]
    for stage, load, variants in stages:
        for variant in variants:
            v = load(variant)
            if v is None:
                continue
            for view, paper_name in TAB_I_METHODS[variant]:
                w = v["views"].get(view)
                if w is not None:
                    method = PAPER_NAMES[variant] if variant != "ago" else TAB_I_AGO_VIEWS[view]
                    t["rows"].append({"stage": stage, "method": method,
                                      "paper_method": paper_name, "iou": w["metric"]["iou"], **_row(w)})
    t["missing"] = sorted(set(t["missing"]))
    return t


# ---------------------------------------------------------------------------------------------
# Occ3D-Waymo: Tab. G (closed world) and Tab. H (open world), each stage beside the paper's AGO row
PAPER_AGO = "AGO (ours)"
WAYMO_STAGES = (("pretraining", "Pretraining"), ("zero-shot", "Zero-shot Evaluation"),
                ("few-shot", "Few-shot Finetuning"))


def _paper_ago_rows(paper: dict | None, key: str) -> list[dict]:
    """The paper's AGO rows of paper table `key` ([] without the paper's tables)."""
    return [r for r in ((paper or {}).get(key) or {}).get("rows", []) if r.get("method") == PAPER_AGO]


def table_g(out: Path, profile: ExperimentProfile, paper: dict | None = None) -> dict:
    """Tab. G: the closed-world run on the synthetic Occ3D-Waymo city (15 classes), beside the paper's AGO row."""
    t = {"title": "Tab. G — closed world, self-supervised, Occ3D-Waymo layout (15 classes, val split; mean of "
                  f"seeds {list(profile.seeds)})", "classes": list(OCC3D_WAYMO.names), "rows": [], "missing": []}
    v = _views(out, waymo_run("cw").name, profile.seeds, t["missing"])
    if v is not None:
        view = v["views"]["cw"]
        t["rows"].append({"method": "ago (ours, synthetic Waymo city)", "mIoU": view["mIoU"],
                          "geometry_IoU": view["geometry_IoU"],
                          "iou": {c: view["metric"]["iou"].get(c) for c in t["classes"]}})
    scores = out / "data_scores_waymo.json"
    if v is not None and scores.is_file():
        ps = read_json(scores)["pseudo_cw_val"]
        t["rows"].append({"method": "pseudo-labels themselves (val frames)", "mIoU": ps["mIoU"],
                          "geometry_IoU": ps["geometry_IoU"], "iou": {c: ps["iou"].get(c) for c in t["classes"]}})
    for r in _paper_ago_rows(paper, "tabG_waymo_closed_world"):
        t["rows"].append({"method": "paper: AGO (ours), Tab. G", "mIoU": r["mIoU"], "geometry_IoU": None,
                          "iou": {c: r["iou"].get(c) for c in t["classes"]}, "paper": True})
    return t


def waymo_h_classes() -> tuple[list[str], list[str]]:
    """Tab. H's columns: (known, unknown) class names in the paper's order, the pretraining stage's supercategory
    (cycle) after the known classes of the evaluation label space (prompts/waymo/ow_waymo.txt)."""
    from ago_runtime.vocab.prompts import parse_prompt_file

    ev = parse_prompt_file(shipped_prompts(PROMPTS["waymo"]["ow"]))
    pre = parse_prompt_file(shipped_prompts(WAYMO_PRETRAIN_EVAL))
    known = [c for c in ev.class_names if c in ev.known]
    known += [c for c in pre.class_names if c in pre.known and c not in known]
    return known, [c for c in ev.class_names if c not in ev.known]


def table_h(out: Path, profile: ExperimentProfile, paper: dict | None = None) -> dict:
    """Tab. H: the open-world runs on the synthetic Occ3D-Waymo city in the paper's three stages (known / unknown /
    all mIoU and per class), each beside the paper's AGO row of that stage."""
    known, unknown = waymo_h_classes()
    t = {"title": "Tab. H — open world, Occ3D-Waymo layout: pretraining on pedestrian, road, sidewalk, vehicle, "
                  f"cycle; zero-shot and few-shot (k={profile.k}) on 14 classes (AGO's min-entropy identifier; "
                  f"mean of seeds {list(profile.seeds)})",
         "known": known, "unknown": unknown, "rows": [], "missing": []}
    pre = _views(out, waymo_run("ow").name, profile.seeds, t["missing"])
    few = _views_of(out, [waymo_run("fewshot", s).name for s in profile.seeds], t["missing"])
    ours = {"pretraining": pre and pre["views"]["ow-pretrain"], "zero-shot": pre and pre["views"]["ow-min-entropy"],
            "few-shot": few and few["views"]["ow-min-entropy"]}
    papers = {r["stage"]: r for r in _paper_ago_rows(paper, "tabH_waymo_open_world")}
    for stage, paper_stage in WAYMO_STAGES:
        view = ours[stage]
        if view:
            t["rows"].append({"stage": stage, "method": "ago (ours, synthetic Waymo city)", **_row(view),
                              "iou": {c: view["metric"]["iou"].get(c) for c in known + unknown}})
        r = papers.get(paper_stage)
        if r:
            t["rows"].append({"stage": stage, "method": "paper: AGO (ours), Tab. H", "known": r["known_mIoU"],
                              "unknown": r["unknown_mIoU"], "all": r["mIoU"],
                              "iou": {c: r["iou"].get(c) for c in known + unknown}, "paper": True})
    t["missing"] = sorted(set(t["missing"]))
    return t


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
                spread = ", above the seed spread" if _separated(f, z) else ", within the seed spread"
            text += (f"; few-shot fine-tuning {'raises' if f > z else 'does not raise'} our unknown mIoU "
                     f"({float(f) - float(z):+.2f}{spread}), {'as' if same else 'unlike'} the paper's "
                     f"({pf - pz:+.2f})")
    return ["", text + "."]


# ---------------------------------------------------------------------------------------------
def _md_table(header: list[str], rows: list[list]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        lines.append("| " + " | ".join(x if isinstance(x, str) else _fmt(x) for x in r) + " |")
    return lines


# ---------------------------------------------------------------------------------------------
# the paper's tables, printed under ours
def read_paper_tables() -> dict | None:
    """paper_tables.json as a dict, or None when the file is absent."""
    return json.loads(PAPER_TABLES.read_text(encoding="utf-8")) if PAPER_TABLES.is_file() else None


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


def ow_split() -> tuple[list[str], list[str]]:
    """This driver's open-world split: (known, unknown) class names of prompts/ow.txt, in its order."""
    from ..open_world import open_world_label_space

    space = open_world_label_space("ow", "ow_pretrain")
    return ([c for c in space.class_names if c in space.known], [c for c in space.class_names if c not in space.known])


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
        lines += _md_table([title for title, _ in cols], [[cell(r) for _, cell in cols] for r in t["rows"]])
        if comment:
            lines += ["", comment]
        if t.get("ambiguity"):
            lines += ["", f"In the paper: {t['ambiguity']}."]
        if t.get("consistency"):
            lines += ["", f"Checked against the paper's per-class cells: {t['consistency']}."]
    return lines


def _fmt_s(v) -> str:
    return "–" if v is None else f"{v:.0f}"


def markdown(tables: dict, profile: ExperimentProfile, steps: dict, paper: dict | None = None,
             times: dict | None = None) -> str:
    L = [f"# Experiments (profile `{profile.name}`)", "",
         "Synthetic world, simulated VLM backends (see docs/synth.md, docs/vlm_files.md); numbers in % over "
         "the val split's camera-visible voxels at the GT resolution. Made by `ago experiments run --profile "
         f"{profile.name}`; see docs/results.md for the reading beside the paper. Every run is trained with "
         f"the seeds {list(profile.seeds)}: a cell is the mean, each seed's value in brackets; under each "
         "table a line says which differences are above the seed spread (the seeds' ranges do not overlap).", ""]
    t1 = tables["tab1"]
    L += [f"## {t1['title']}", ""]
    if t1["rows"]:
        classes = [c for c in OCC3D_CLASSES]
        L += _md_table(["method", "mIoU", "mIoU*", "geo IoU"] + classes,
                       [[r["method"], r["mIoU"], r["mIoU_star"], r["geometry_IoU"]]
                        + [_plain(r["iou"].get(c)) for c in classes]
                        for r in t1["rows"]])
    L += spread_note(t1["rows"][:2], "mIoU", lambda r: r["method"], t1["rows"][0], "mIoU") if t1["rows"] else []
    L += _missing(t1)
    L += paper_markdown(paper, "tab1")
    t2 = tables["tab2"]
    L += ["", f"## {t2['title']}", ""]
    L += _md_table(["method", "stage", "known", "unknown", "all"],
                   [[r["method"], r["stage"], r["known"], r["unknown"], r["all"]] for r in t2["rows"]])
    for stage in dict.fromkeys(r["stage"] for r in t2["rows"]):
        rows = [r for r in t2["rows"] if r["stage"] == stage]
        ref = [r for r in rows if r["method"] == PAPER_NAMES["ago"]]
        if ref:
            L += spread_note(rows, "unknown", lambda r: r["method"], ref[0], f"{stage}, unknown mIoU")
    L += _missing(t2)
    L += paper_markdown(paper, "tab2")
    t3 = tables["tab3"]
    L += ["", f"## {t3['title']}", ""]
    L += _md_table(["paradigm", "cw mIoU", "cw geo IoU", "ow known", "ow unknown", "ow all"],
                   [[r["paradigm"], r["cw_mIoU"], r["cw_geometry_IoU"], r["ow_known"], r["ow_unknown"], r["ow_all"]]
                    for r in t3["rows"]])
    ref = [r for r in t3["rows"] if r["paradigm"] == PAPER_NAMES["ago"]]
    for key, what in (("cw_mIoU", "closed-world mIoU"), ("ow_unknown", "zero-shot unknown mIoU")):
        L += spread_note(t3["rows"], key, lambda r: r["paradigm"], ref[0], what) if ref else []
    L += _missing(t3)
    L += paper_markdown(paper, "tab3")
    t4 = tables["tab4"]
    L += ["", f"## {t4['title']}", ""]
    L += _md_table(["identifier", "zero-shot known", "zero-shot unknown", "zero-shot all", "few-shot known",
                    "few-shot unknown", "few-shot all"],
                   [[r["identifier"], r.get("zs_known"), r.get("zs_unknown"), r.get("zs_all"), r.get("fs_known"),
                     r.get("fs_unknown"), r.get("fs_all")] for r in t4["rows"]])
    ref = [r for r in t4["rows"] if r["identifier"] == "min entropy (AGO)"]
    for key, what in (("zs_unknown", "zero-shot unknown mIoU"), ("fs_unknown", "few-shot unknown mIoU")):
        L += spread_note(t4["rows"], key, lambda r: r["identifier"], ref[0], what) if ref else []
    L += _missing(t4)
    L += paper_markdown(paper, "tab4")
    t5 = tables["tab5"]
    L += ["", f"## {t5['title']}", ""]
    L += _md_table(["noise prompts", "L_occ", "geometry IoU", "mIoU"],
                   [["yes" if r["noise_prompts"] else "no", "yes" if r["L_occ"] else "no", r["geometry_IoU"], r["mIoU"]]
                    for r in t5["rows"]])
    name5 = lambda r: f"noise {'yes' if r['noise_prompts'] else 'no'}, L_occ {'yes' if r['L_occ'] else 'no'}"  # noqa: E731
    for key, what in (("mIoU", "mIoU"), ("geometry_IoU", "geometry IoU")):
        L += spread_note(t5["rows"], key, name5, t5["rows"][-1], what) if t5["rows"] else []
    L += _missing(t5)
    L += paper_markdown(paper, "tab5")
    ts = tables["supp"]
    L += ["", f"## {ts['title']}", ""]
    L += _md_table(["adapter layers", "known", "unknown", "all", "unknown (F~ only)"],
                   [[str(r["adapter_layers"]), r["known"], r["unknown"], r["all"], r["unknown_adapted_only"]]
                    for r in ts["depth"]])
    L += [""]
    L += _md_table(["align loss", "known", "unknown", "all", "unknown (F~ only)"],
                   [[r["align_loss"], r["known"], r["unknown"], r["all"], r["unknown_adapted_only"]] for r in ts["loss"]])
    if ts["depth"]:
        L += spread_note(ts["depth"], "unknown", lambda r: f"{r['adapter_layers']} layers", ts["depth"][1],
                         "unknown mIoU")
        L += spread_note(ts["loss"], "unknown", lambda r: r["align_loss"], ts["loss"][0], "unknown mIoU")
    L += _missing(ts)
    L += paper_markdown(paper, "supp")
    ti = tables.get("tabI")
    if ti is not None:
        known, unknown = ow_split()
        L += ["", f"## {ti['title']}", ""]
        L += _md_table(["stage", "method", "paper's row"] + known + unknown + ["known", "unknown", "all"],
                       [[r["stage"], r["method"], r["paper_method"]] + [_plain(r["iou"].get(c)) for c in known + unknown]
                        + [r["known"], r["unknown"], r["all"]] for r in ti["rows"]])
        L += ["", "Known classes first (" + ", ".join(known) + "), then the unknown ones."]
        L += _missing(ti)
        L += paper_markdown(paper, "tabI")
    tg = tables.get("tabG")
    if tg is not None:
        L += ["", f"## {tg['title']}", ""]
        if tg["rows"]:
            L += _md_table(["method", "mIoU", "geo IoU"] + tg["classes"],
                           [[r["method"], r["mIoU"], r["geometry_IoU"]] + [_plain(r["iou"].get(c)) for c in tg["classes"]]
                            for r in tg["rows"]])
        L += waymo_g_note(tg)
        L += _missing(tg)
        L += paper_markdown(paper, "tabG")
    th = tables.get("tabH")
    if th is not None:
        L += ["", f"## {th['title']}", ""]
        if th["rows"]:
            L += _md_table(["stage", "method"] + th["known"] + ["k. mIoU"] + th["unknown"] + ["u. mIoU", "mIoU"],
                           [[r["stage"], r["method"]] + [_plain(r["iou"].get(c)) for c in th["known"]] + [r["known"]]
                            + [_plain(r["iou"].get(c)) for c in th["unknown"]] + [r["unknown"], r["all"]]
                            for r in th["rows"]])
        ours = [r for r in th["rows"] if not r.get("paper")]
        ref = [r for r in ours if r["stage"] == "zero-shot"]
        L += spread_note(ours, "unknown", lambda r: r["stage"], ref[0], "unknown mIoU") if ref else []
        L += waymo_h_note(th)
        L += _missing(th)
        L += paper_markdown(paper, "tabH")
    times = times or {}
    L += ["", "## Runs", "", "| run | optimiser steps | training wall s (its last session) | scoring wall s |",
          "|---|---|---|---|"]
    L += [f"| {k} | {v} | {_fmt_s(times.get(k, {}).get('train_s'))} | {_fmt_s(times.get(k, {}).get('eval_s'))} |"
          for k, v in sorted(steps.items())]
    total = sum((t.get("train_s") or 0) + (t.get("eval_s") or 0) for t in times.values())
    if total:
        L += ["", f"Whole set: {total / 3600:.2f} h of wall-clock time in training and scoring ({len(steps)} runs; "
                  "data making not included)."]
    L += ["", "Figures: " + ", ".join(f"`figures/{p}`" for p in tables.get("figures", [])), ""]
    return "\n".join(L) + "\n"


def _missing(t: dict) -> list[str]:
    return [f"", f"Not run yet: {', '.join(t['missing'])}."] if t.get("missing") else []


# ---------------------------------------------------------------------------------------------
# figures (opencv only)
WHITE, BLACK, GREY = (255, 255, 255), (30, 30, 30), (150, 150, 150)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def bar_chart(title: str, labels: list[str], series: list[tuple[str, list[float], tuple]], marks: list[bool],
              ylabel: str) -> np.ndarray:
    """Grouped vertical bars, one group per label; `marks` underlines the labels that are unknown."""
    n, m = len(labels), len(series)
    bw, gap, left, top, H = 14, 14, 60, 50, 260
    W = left + n * (m * bw + gap) + 20
    img = np.full((top + H + 170, W, 3), 255, np.uint8)
    vmax = max([max(s[1]) for s in series if s[1]] + [1e-6])
    cv2.putText(img, title, (10, 24), FONT, 0.6, BLACK, 1, cv2.LINE_AA)
    cv2.line(img, (left, top + H), (W - 10, top + H), BLACK, 1)
    for t in np.linspace(0, vmax, 5):
        y = int(top + H - H * t / vmax)
        cv2.line(img, (left - 4, y), (W - 10, y), (225, 225, 225), 1)
        cv2.putText(img, f"{t:.2f}", (4, y + 4), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (4, top - 10), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
    for i, lab in enumerate(labels):
        x0 = left + i * (m * bw + gap) + gap // 2
        for j, (_name, vals, col) in enumerate(series):
            h = int(H * vals[i] / vmax)
            cv2.rectangle(img, (x0 + j * bw, top + H - h), (x0 + (j + 1) * bw - 2, top + H), col, -1)
        txt = np.full((18, 140, 3), 255, np.uint8)   # right-aligned, so after rotation it hangs from the axis
        tw = cv2.getTextSize(lab[:20], FONT, 0.4, 1)[0][0]
        cv2.putText(txt, lab[:20], (138 - tw, 13), FONT, 0.4, (200, 0, 0) if marks[i] else BLACK, 1, cv2.LINE_AA)
        rot = cv2.rotate(txt, cv2.ROTATE_90_COUNTERCLOCKWISE)
        ys, xs = top + H + 4, x0 + (m * bw) // 2 - 9
        img[ys:ys + rot.shape[0], xs:xs + rot.shape[1]] = np.minimum(img[ys:ys + rot.shape[0], xs:xs + rot.shape[1]], rot)
    x = W - 10 - 170 * m
    for j, (name, _vals, col) in enumerate(series):
        cv2.rectangle(img, (x + 170 * j, 34), (x + 170 * j + 12, 46), col, -1)
        cv2.putText(img, name, (x + 170 * j + 16, 45), FONT, 0.42, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, "red labels: unknown classes", (left, img.shape[0] - 8), FONT, 0.4, (200, 0, 0), 1, cv2.LINE_AA)
    return img


def heatmap(title: str, rows: list[str], cols: list[str], values: np.ndarray, cell: int = 26) -> np.ndarray:
    """A matrix as coloured cells (viridis over its own range) with row / column names and values."""
    v = np.asarray(values, dtype=np.float64)
    lo, hi = float(np.nanmin(v)), float(np.nanmax(v))
    norm = np.clip((v - lo) / max(hi - lo, 1e-9), 0, 1)
    col = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[:, :, ::-1]
    left, top = 150, 150
    img = np.full((top + cell * len(rows) + 40, left + cell * len(cols) + 20, 3), 255, np.uint8)
    cv2.putText(img, title, (6, 20), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, f"rows: GT class; columns: class text; range {lo:.2f}..{hi:.2f}", (6, 40), FONT, 0.38,
                BLACK, 1, cv2.LINE_AA)
    for i in range(len(rows)):
        cv2.putText(img, rows[i][:20], (4, top + cell * i + cell - 8), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
        for j in range(len(cols)):
            y, x = top + cell * i, left + cell * j
            img[y:y + cell - 1, x:x + cell - 1] = col[i, j]
            if i == j:
                cv2.rectangle(img, (x, y), (x + cell - 2, y + cell - 2), (255, 60, 60), 1)
    for j in range(len(cols)):
        txt = np.full((16, top - 50, 3), 255, np.uint8)
        tw = cv2.getTextSize(cols[j][:16], FONT, 0.38, 1)[0][0]
        cv2.putText(txt, cols[j][:16], (top - 52 - tw, 12), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
        rot = cv2.rotate(txt, cv2.ROTATE_90_COUNTERCLOCKWISE)
        x = left + cell * j + (cell - 16) // 2
        img[top - rot.shape[0] - 2:top - 2, x:x + 16] = rot
    return img


def figures(out: Path, profile: ExperimentProfile, gap_e3d: dict | None) -> list[str]:
    from ago_runtime.pictures.render import save_png, side_by_side, stack_vertical

    fig_dir = out / "figures"
    made = []
    ow = _views(out, ow_run("ago").name)
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


def _to_occ3d(labels: np.ndarray, class_names: list[str]) -> np.ndarray:
    """Label-space ids (K = free) -> Occ3D ids by class name (17 = free; names not in Occ3D -> 255)."""
    lut = np.full(256, 255, np.uint8)
    for k, c in enumerate(class_names):
        if c in OCC3D_CLASSES:
            lut[k] = OCC3D_CLASSES.index(c)
    lut[len(class_names)] = 17
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
            return voxel_view(np.where(mask, labels, 17).astype(np.uint8), scale=scale, crop=False)

        panels = [("GT", view(gt.semantics))]
        try:
            sem, _ml, _mc = load_pseudo_labels(pseudo_dir, scene, token)
            sem = np.where(sem == 255, 17, sem).astype(np.uint8)
            panels.append(("pseudo-labels", view(upsample_nearest(sem, fac))))
        except Exception:  # noqa: BLE001 - a frame without pseudo-labels is drawn without that panel
            pass
        cw_occ = _to_occ3d(cw_pred, cw_names)
        panels.append(("ago (cw)", view(upsample_nearest(cw_occ, fac))))
        g = ow_dir / f"ow-min-entropy__{token}.npz"
        if g.is_file():
            with open_npz(g, "kept prediction") as z:
                ow_occ = _to_occ3d(z["labels"], ow_names)
            panels.append(("ago zero-shot (ow)", view(upsample_nearest(ow_occ, fac))))
        rows.append(side_by_side(panels))
    if rows:
        rows.insert(0, _caption("Val frames, camera-visible voxels: GT | cw pseudo-labels | ago closed world | "
                                "ago zero-shot on the 15 ow classes (min-entropy)",
                                rows[0].shape[1]))
        rows.append(legend(list(OCC3D_CLASSES), width=rows[0].shape[1]))
    return rows


# ---------------------------------------------------------------------------------------------
def write_report(out: str | Path, profile: ExperimentProfile) -> dict:
    out = Path(out)
    extra = read_json(out / "data_scores.json") if (out / "data_scores.json").is_file() else {}
    paper = read_paper_tables()
    tables = {"tab1": table1(out, extra.get("pseudo_cw_val"), profile), "tab2": table2(out, profile),
              "tab3": table3(out, profile), "tab4": table4(out, profile), "tab5": table5(out, profile),
              "supp": table_supp(out, profile), "tabI": table_i(out, profile),
              "tabG": table_g(out, profile, paper), "tabH": table_h(out, profile, paper)}
    tables["figures"] = figures(out, profile, extra.get("gap_e3d"))
    steps = {p.parent.relative_to(out / "runs").as_posix(): read_json(p).get("steps")
             for p in sorted((out / "runs").glob("**/done.json"))} if (out / "runs").is_dir() else {}
    times = {}
    for name in steps:
        done, views = out / "runs" / name / "done.json", out / "runs" / name / "views.json"
        times[name] = {"train_s": read_json(done).get("wall_s_last_session"),
                       "eval_s": read_json(views).get("eval_s") if views.is_file() else None}
    md = markdown(tables, profile, steps, paper, times)
    result = {"profile": profile.to_dict(), "tables": _per_seed(tables), "steps": steps, "times": times,
              "paper": paper}
    write_json(out / "results.json", result)
    write_text(out / "results.md", md)
    return result
