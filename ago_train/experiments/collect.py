"""What the runs of an experiments folder measured, read back for the tables (driver.py writes it).

- `views(out, name, seeds)` / `views_of(out, names)`: the runs' `runs/<name>/views.json` merged over seeds into
  `SeedMean`s (a float that keeps each seed's value; `fmt` prints it 'mean (a, b)', `separated` says whether two
  seed means' ranges do not overlap); absent runs are listed in `missing`.
- `run_records(out)`: each finished run's optimiser steps and wall-clock seconds (training, scoring).
- `per_seed(tables)`: results.json keeps every seed's value beside each mean.
- `ow_split()`, `waymo_h_classes()`: the known / unknown classes of the open-world label spaces, in the order
  the tables print them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ago_runtime.readers import read_json

from .plan import PROMPTS, WAYMO_PRETRAIN_EVAL, seeded, shipped_prompts

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

def views_of(out: Path, names: list[str], missing: list | None = None) -> dict | None:
    """The views.json of the runs `names` (one per seed) merged into means; absent runs go to `missing`."""
    got = []
    for name in names:
        p = out / "runs" / name / "views.json"
        if p.is_file():
            got.append(read_json(p))
        elif missing is not None:
            missing.append(name)
    return _merge(got) if got else None

def views(out: Path, name: str, seeds=(0,), missing: list | None = None) -> dict | None:
    return views_of(out, [seeded(name, s) for s in seeds], missing)

def fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, SeedMean) and len(v.values) > 1:
        return f"{v:.2f} ({', '.join(f'{x:.2f}' for x in v.values)})"
    return f"{v:.2f}"

def separated(a, b) -> bool:
    """True when two seed means' ranges of values do not overlap (the difference is above the seed spread)."""
    return min(a.values) > max(b.values) or max(a.values) < min(b.values)

def per_seed(tables: dict) -> dict:
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

def run_records(out: Path) -> tuple[dict, dict]:
    """(steps, times) of the finished runs (those with a done.json): run name -> optimiser steps, and run name ->
    {"train_s": wall seconds of its last training session, "eval_s": its scoring's wall seconds or None}."""
    steps = {p.parent.relative_to(out / "runs").as_posix(): read_json(p).get("steps")
             for p in sorted((out / "runs").glob("**/done.json"))} if (out / "runs").is_dir() else {}
    times = {}
    for name in steps:
        done, scored = out / "runs" / name / "done.json", out / "runs" / name / "views.json"
        times[name] = {"train_s": read_json(done).get("wall_s_last_session"),
                       "eval_s": read_json(scored).get("eval_s") if scored.is_file() else None}
    return steps, times


def ow_split() -> tuple[list[str], list[str]]:
    """This driver's open-world split: (known, unknown) class names of prompts/ow.txt, in its order."""
    from ..open_world import open_world_label_space

    space = open_world_label_space("ow", "ow_pretrain")
    return ([c for c in space.class_names if c in space.known], [c for c in space.class_names if c not in space.known])

def waymo_h_classes() -> tuple[list[str], list[str]]:
    """Tab. H's columns: (known, unknown) class names in the paper's order, the pretraining stage's supercategory
    (cycle) after the known classes of the evaluation label space (prompts/waymo/ow_waymo.txt)."""
    from ago_runtime.vocab.prompts import parse_prompt_file

    ev = parse_prompt_file(shipped_prompts(PROMPTS["waymo"]["ow"]))
    pre = parse_prompt_file(shipped_prompts(WAYMO_PRETRAIN_EVAL))
    known = [c for c in ev.class_names if c in ev.known]
    known += [c for c in pre.class_names if c in pre.known and c not in known]
    return known, [c for c in ev.class_names if c not in ev.known]
