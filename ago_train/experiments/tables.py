"""Our tables (markdown + JSON) from the runs of an experiments folder (collect.py reads them).

`table1` ... `table_h` each build one of the paper's tables from the runs that exist (a table with missing runs
says which); `markdown(tables, ...)` prints them, each with the line on which differences are above the seed
spread (`spread_note`) and the paper's table under it (paper.py).
"""

from __future__ import annotations

from pathlib import Path

from ago_runtime.classes import OCC3D_CLASSES, OCC3D_WAYMO
from ago_runtime.readers import read_json

from .collect import SeedMean, ow_split, separated, views, views_of, waymo_h_classes
from .paper import WAYMO_STAGES, md_table, paper_ago_rows, paper_markdown, waymo_g_note, waymo_h_note
from .plan import (ADAPTED_SCALES, FEWSHOT_VARIANTS, PARADIGMS, ExperimentProfile, cw_run, fewshot_run, ow_run,
                   waymo_run)

PAPER_NAMES = {"align": "POP-3D-like align", "grounding": "grounding only", "grounding+align": "grounding + align",
               "ago": "AGO (adaptive grounding)", "closed": "closed-world classifier (SelfOcc-like)"}


def _plain(v):
    """A seed mean printed without its seed values (the per-class columns)."""
    return None if v is None else float(v)

def _row(view: dict | None) -> dict:
    if view is None:
        return {"known": None, "unknown": None, "all": None}
    sub = view.get("subsets") or {}
    return {"known": sub.get("known"), "unknown": sub.get("unknown"), "all": view["mIoU"]}

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
        (above if separated(v, r0) else within).append(f"{label(r)} {v - r0:+.2f}")
    if not above and not within:
        return []
    return ["", f"Seed spread ({what}, against {label(ref)}): above the spread (the seeds' ranges do not "
                f"overlap): {'; '.join(above) or 'none'}. Within the spread: {'; '.join(within) or 'none'}."]


# ---------------------------------------------------------------------------------------------
# every number below is the mean over the profile's seeds (a SeedMean that keeps each seed's value)
def table1(out: Path, pseudo_score: dict | None, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 1 — closed world, self-supervised (cw label space, val split)", "rows": [], "missing": []}
    v = views(out, cw_run("ago").name, profile.seeds, t["missing"])
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
    cl = views(out, ow_run("grounding").name, profile.seeds)
    if cl and "ow-closed" in cl["views"]:
        t["rows"].append({"method": PAPER_NAMES["closed"], "stage": "zero-shot", **_row(cl["views"]["ow-closed"])})
    for variant in FEWSHOT_VARIANTS:
        view = "ow-min-entropy" if variant == "ago" else "ow-none"
        v = views(out, ow_run(variant).name, profile.seeds, t["missing"])
        if v is not None:
            t["rows"].append({"method": PAPER_NAMES[variant], "stage": "zero-shot", **_row(v["views"][view])})
        f = views_of(out, [fewshot_run(variant, s).name for s in profile.seeds], t["missing"])
        if f is not None:
            t["rows"].append({"method": PAPER_NAMES[variant], "stage": f"{profile.k}-shot", **_row(f["views"][view])})
    return t

def table3(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 3 — training paradigm: self-supervised (cw mIoU) and open world (zero-shot, known / "
                  "unknown / all)", "rows": [], "missing": []}
    for variant in PARADIGMS:
        cw = views(out, cw_run(variant).name, profile.seeds, t["missing"])
        ow = views(out, ow_run(variant).name, profile.seeds, t["missing"])
        ow_view = "ow-min-entropy" if variant == "ago" else "ow-none"
        t["rows"].append({"paradigm": PAPER_NAMES[variant],
                          "cw_mIoU": cw["views"]["cw"]["mIoU"] if cw else None,
                          "cw_geometry_IoU": cw["views"]["cw"]["geometry_IoU"] if cw else None,
                          **{f"ow_{k}": x for k, x in _row(ow["views"][ow_view] if ow else None).items()}})
    return t

def table4(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Tab. 4 — open-world identifier (ago; known / unknown / all mIoU)", "rows": [], "missing": []}
    zs = views(out, ow_run("ago").name, profile.seeds, t["missing"])
    fs = views_of(out, [fewshot_run("ago", s).name for s in profile.seeds], t["missing"])
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
        v = views(out, cw_run("ago", **loss).name, profile.seeds, t["missing"])
        view = v["views"]["cw"] if v else None
        t["rows"].append({"noise_prompts": noise, "L_occ": occ, "geometry_IoU": view["geometry_IoU"] if view else None,
                          "mIoU": view["mIoU"] if view else None})
    return t

def table_supp(out: Path, profile: ExperimentProfile) -> dict:
    t = {"title": "Supplementary — adapter depth and alignment loss (ago, open world zero-shot, min-entropy)",
         "depth": [], "loss": [], "missing": []}

    def row(spec) -> dict:
        v = views(out, spec.name, profile.seeds, t["missing"])
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
    stages = [("zero-shot", lambda v: views(out, ow_run(v).name, profile.seeds, t["missing"]), PARADIGMS),
              (f"{profile.k}-shot", lambda v: views_of(out, [fewshot_run(v, s).name for s in profile.seeds],
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


# Occ3D-Waymo: Tab. G (closed world) and Tab. H (open world), each stage beside the paper's AGO row
def table_g(out: Path, profile: ExperimentProfile, paper: dict | None = None) -> dict:
    """Tab. G: the closed-world run on the synthetic Occ3D-Waymo city (15 classes), beside the paper's AGO row."""
    t = {"title": "Tab. G — closed world, self-supervised, Occ3D-Waymo layout (15 classes, val split; mean of "
                  f"seeds {list(profile.seeds)})", "classes": list(OCC3D_WAYMO.names), "rows": [], "missing": []}
    v = views(out, waymo_run("cw").name, profile.seeds, t["missing"])
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
    for r in paper_ago_rows(paper, "tabG_waymo_closed_world"):
        t["rows"].append({"method": "paper: AGO (ours), Tab. G", "mIoU": r["mIoU"], "geometry_IoU": None,
                          "iou": {c: r["iou"].get(c) for c in t["classes"]}, "paper": True})
    return t

def table_h(out: Path, profile: ExperimentProfile, paper: dict | None = None) -> dict:
    """Tab. H: the open-world runs on the synthetic Occ3D-Waymo city in the paper's three stages (known / unknown /
    all mIoU and per class), each beside the paper's AGO row of that stage."""
    known, unknown = waymo_h_classes()
    t = {"title": "Tab. H — open world, Occ3D-Waymo layout: pretraining on pedestrian, road, sidewalk, vehicle, "
                  f"cycle; zero-shot and few-shot (k={profile.k}) on 14 classes (AGO's min-entropy identifier; "
                  f"mean of seeds {list(profile.seeds)})",
         "known": known, "unknown": unknown, "rows": [], "missing": []}
    pre = views(out, waymo_run("ow").name, profile.seeds, t["missing"])
    few = views_of(out, [waymo_run("fewshot", s).name for s in profile.seeds], t["missing"])
    ours = {"pretraining": pre and pre["views"]["ow-pretrain"], "zero-shot": pre and pre["views"]["ow-min-entropy"],
            "few-shot": few and few["views"]["ow-min-entropy"]}
    papers = {r["stage"]: r for r in paper_ago_rows(paper, "tabH_waymo_open_world")}
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


# ---------------------------------------------------------------------------------------------
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
        L += md_table(["method", "mIoU", "mIoU*", "geo IoU"] + classes,
                       [[r["method"], r["mIoU"], r["mIoU_star"], r["geometry_IoU"]]
                        + [_plain(r["iou"].get(c)) for c in classes]
                        for r in t1["rows"]])
    L += spread_note(t1["rows"][:2], "mIoU", lambda r: r["method"], t1["rows"][0], "mIoU") if t1["rows"] else []
    L += _missing(t1)
    L += paper_markdown(paper, "tab1")
    t2 = tables["tab2"]
    L += ["", f"## {t2['title']}", ""]
    L += md_table(["method", "stage", "known", "unknown", "all"],
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
    L += md_table(["paradigm", "cw mIoU", "cw geo IoU", "ow known", "ow unknown", "ow all"],
                   [[r["paradigm"], r["cw_mIoU"], r["cw_geometry_IoU"], r["ow_known"], r["ow_unknown"], r["ow_all"]]
                    for r in t3["rows"]])
    ref = [r for r in t3["rows"] if r["paradigm"] == PAPER_NAMES["ago"]]
    for key, what in (("cw_mIoU", "closed-world mIoU"), ("ow_unknown", "zero-shot unknown mIoU")):
        L += spread_note(t3["rows"], key, lambda r: r["paradigm"], ref[0], what) if ref else []
    L += _missing(t3)
    L += paper_markdown(paper, "tab3")
    t4 = tables["tab4"]
    L += ["", f"## {t4['title']}", ""]
    L += md_table(["identifier", "zero-shot known", "zero-shot unknown", "zero-shot all", "few-shot known",
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
    L += md_table(["noise prompts", "L_occ", "geometry IoU", "mIoU"],
                   [["yes" if r["noise_prompts"] else "no", "yes" if r["L_occ"] else "no", r["geometry_IoU"], r["mIoU"]]
                    for r in t5["rows"]])
    name5 = lambda r: f"noise {'yes' if r['noise_prompts'] else 'no'}, L_occ {'yes' if r['L_occ'] else 'no'}"  # noqa: E731
    for key, what in (("mIoU", "mIoU"), ("geometry_IoU", "geometry IoU")):
        L += spread_note(t5["rows"], key, name5, t5["rows"][-1], what) if t5["rows"] else []
    L += _missing(t5)
    L += paper_markdown(paper, "tab5")
    ts = tables["supp"]
    L += ["", f"## {ts['title']}", ""]
    L += md_table(["adapter layers", "known", "unknown", "all", "unknown (F~ only)"],
                   [[str(r["adapter_layers"]), r["known"], r["unknown"], r["all"], r["unknown_adapted_only"]]
                    for r in ts["depth"]])
    L += [""]
    L += md_table(["align loss", "known", "unknown", "all", "unknown (F~ only)"],
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
        L += md_table(["stage", "method", "paper's row"] + known + unknown + ["known", "unknown", "all"],
                       [[r["stage"], r["method"], r["paper_method"]] + [_plain(r["iou"].get(c)) for c in known + unknown]
                        + [r["known"], r["unknown"], r["all"]] for r in ti["rows"]])
        L += ["", "Known classes first (" + ", ".join(known) + "), then the unknown ones."]
        L += _missing(ti)
        L += paper_markdown(paper, "tabI")
    tg = tables.get("tabG")
    if tg is not None:
        L += ["", f"## {tg['title']}", ""]
        if tg["rows"]:
            L += md_table(["method", "mIoU", "geo IoU"] + tg["classes"],
                           [[r["method"], r["mIoU"], r["geometry_IoU"]] + [_plain(r["iou"].get(c)) for c in tg["classes"]]
                            for r in tg["rows"]])
        L += waymo_g_note(tg)
        L += _missing(tg)
        L += paper_markdown(paper, "tabG")
    th = tables.get("tabH")
    if th is not None:
        L += ["", f"## {th['title']}", ""]
        if th["rows"]:
            L += md_table(["stage", "method"] + th["known"] + ["k. mIoU"] + th["unknown"] + ["u. mIoU", "mIoU"],
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
    return ["", f"Not run yet: {', '.join(t['missing'])}."] if t.get("missing") else []
