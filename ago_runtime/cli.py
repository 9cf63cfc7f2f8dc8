"""The `ago` command line (typer).

Each verb lives in a small command module that imports nothing heavy at import time
(torch is imported inside the command), so `ago infer` works on a runtime-only install and
`ago train` says which extra to install when torch is missing. Bad input raises
AgoInputError, which becomes a one-line `error: <file>: <problem>` and exit code 2.
"""

from __future__ import annotations

import importlib
import sys

import typer

from .errors import AgoInputError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="ago: open-world 3D semantic occupancy from surround cameras (AGO, ICCV 2025).")

# Each module defines `register(app)`. Order = order in `ago --help`.
COMMAND_MODULES = (
    "ago_runtime.cli_infer",     # ago infer, ago demo, ago retrieve
    "ago_runtime.cli_prompts",   # ago prompts build|show
    "ago_runtime.cli_show",      # ago show, ago metric
    "ago_train.cli_synth",       # ago synth
    "ago_train.cli_pseudo",      # ago pseudo-labels
    "ago_train.cli_train",       # ago train, ago eval, ago open-world
    "ago_train.cli_experiments", # ago experiments run|report|list
    "ago_export.cli_export",     # ago export
)

for _name in COMMAND_MODULES:
    try:
        _mod = importlib.import_module(_name)
    except ModuleNotFoundError as _e:  # a part not installed (or not written yet) just has no verbs
        if _e.name is not None and _name.startswith(_e.name):
            continue
        raise
    _mod.register(app)


def main() -> None:
    try:
        app(standalone_mode=False)
    except AgoInputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except MissingExtra as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except SystemExit:
        raise
    except Exception as e:  # click's usage errors
        import click

        if isinstance(e, click.exceptions.ClickException):
            e.show()
            sys.exit(2)
        if isinstance(e, click.exceptions.Abort):
            sys.exit(1)
        raise


class MissingExtra(RuntimeError):
    pass


def require_torch(verb: str) -> None:
    """Call at the top of a verb that needs torch: a clear message instead of an ImportError trace."""
    import importlib.util

    if importlib.util.find_spec("torch") is None:  # look, don't import: the runtime never loads torch
        raise MissingExtra(f"`ago {verb}` needs the training extra: pip install -e '.[train]' "
                           "(and scripts/setup.sh for the bundled weights)")


if __name__ == "__main__":
    main()
