"""CLI verb `ago experiments`: the paper's tables on the synthetic benchmark (ago_train/experiments/).

    ago experiments run [tab1 tab2 tab3 tab4 tab5 supp figures tabG tabH | all] [--profile cpu]
                        [--out runs/experiments]   (tabG / tabH: Occ3D-Waymo, on their own synthetic city)
                        [--records DIR]     (run records reused on another machine: records.py)
    ago experiments report [--profile cpu] [--out runs/experiments]
    ago experiments list [--profile cpu]
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import List, Optional

import typer

from .plan import PROFILES

# --profile's choices, an Enum so that typer derives its help and its check (plan.ExperimentProfile.preset)
Profile = Enum("Profile", {name: name for name in PROFILES}, type=str)


def register(app: typer.Typer) -> None:
    from ago_runtime.cli import verb_group

    exp = verb_group("Run the paper's experiments (tables + figures) on the synthetic benchmark.")
    app.add_typer(exp, name="experiments")

    def _profile(profile: Profile):
        from .plan import ExperimentProfile

        return ExperimentProfile.preset(profile.value)

    @exp.command("run")
    def run_cmd(
        names: Optional[List[str]] = typer.Argument(None, help="experiments to run (default: all)"),
        profile: Profile = typer.Option(Profile("cpu"), "--profile", help="docs/experiments.md"),
        out: Path = typer.Option(Path("runs/experiments"), "--out", help="experiments folder (cache; resumable)"),
        records: Optional[Path] = typer.Option(None, "--records", help="folder of run records (scores, no "
                                               "checkpoints) kept up to date and reused, also on another machine"),
    ):
        """Make or reuse the data, train or reuse the runs, score them, write results.md + figures."""
        from ago_runtime.errors import require_torch

        require_torch("experiments run")
        from ago_runtime.errors import AgoInputError
        from ago_runtime.outputs import check_output_dir

        from .driver import EXPERIMENTS, ExperimentRunner

        chosen = list(EXPERIMENTS) if not names or names == ["all"] else list(names)
        unknown = [n for n in chosen if n not in EXPERIMENTS]
        if unknown:
            raise AgoInputError("NAMES", f"unknown experiment(s) {unknown}; choose from {', '.join(EXPERIMENTS)} or all")
        prof = _profile(profile)
        check_output_dir(out, "--out")
        if records is not None:
            check_output_dir(records, "--records")
        ExperimentRunner(prof, out, records=records).run(chosen)
        typer.echo(f"written {out}/results.md, {out}/results.json, {out}/figures/")

    @exp.command("report")
    def report_cmd(
        profile: Profile = typer.Option(Profile("cpu"), "--profile"),
        out: Path = typer.Option(Path("runs/experiments"), "--out"),
    ):
        """Rewrite results.md / results.json / figures from the runs that exist (trains nothing)."""
        from ago_runtime.outputs import check_output_dir

        from .report import write_report

        prof = _profile(profile)
        check_output_dir(out, "--out")
        write_report(out, prof)
        typer.echo(f"written {out}/results.md, {out}/results.json, {out}/figures/")

    @exp.command("list")
    def list_cmd(profile: Profile = typer.Option(Profile("cpu"), "--profile")):
        """Each experiment and the training runs it needs."""
        from .driver import EXPERIMENTS, runs_for

        p = _profile(profile)
        for e in EXPERIMENTS:
            typer.echo(f"{e}: " + ", ".join(s.name for s in runs_for(e, p)))
