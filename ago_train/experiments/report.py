"""Tables (markdown + JSON) and figures from an experiments folder (see driver.py for its layout).

`write_report(out, profile)` reads every `runs/<name>/views.json` that exists (collect.py), builds the
tables whose runs are there (tables.py; a table with missing runs says which) with the paper's table under
each (paper.py), draws the figures (figures.py), and writes `<out>/results.json`, `<out>/results.md` and
`<out>/figures/*.png`. It trains nothing.
"""

from __future__ import annotations

from pathlib import Path

from ago_runtime.atomic import write_json, write_text
from ago_runtime.readers import read_json

from .collect import per_seed, run_records
from .figures import figures
from .paper import read_paper_tables
from .plan import ExperimentProfile
from .tables import markdown, table1, table2, table3, table4, table5, table_g, table_h, table_i, table_supp


def write_report(out: str | Path, profile: ExperimentProfile) -> dict:
    """Write results.json, results.md and the figures of the experiments folder `out`; -> results.json's dict."""
    out = Path(out)
    extra = read_json(out / "data_scores.json") if (out / "data_scores.json").is_file() else {}
    paper = read_paper_tables()
    tables = {"tab1": table1(out, extra.get("pseudo_cw_val"), profile), "tab2": table2(out, profile),
              "tab3": table3(out, profile), "tab4": table4(out, profile), "tab5": table5(out, profile),
              "supp": table_supp(out, profile), "tabI": table_i(out, profile),
              "tabG": table_g(out, profile, paper), "tabH": table_h(out, profile, paper)}
    tables["figures"] = figures(out, profile, extra.get("gap_e3d"))
    steps, times = run_records(out)
    md = markdown(tables, profile, steps, paper, times)
    result = {"profile": profile.to_dict(), "tables": per_seed(tables), "steps": steps, "times": times,
              "paper": paper}
    write_json(out / "results.json", result)
    write_text(out / "results.md", md)
    return result
