"""The `ago` command line (typer): the app, the table of verb modules, and the one error path.

Verbs live next to what they drive, each module defining `register(app)`:
ago_runtime/predict/cli.py (infer, demo, retrieve), ago_runtime/vocab/cli.py (prompts build|show),
ago_runtime/pictures/cli.py (show), ago_runtime/scoring/cli.py (metric), and in the training
packages ago_train/text/cli.py (prompts export-encoder|noise), ago_train/synth/cli.py (synth),
ago_train/pseudo/cli.py (pseudo-labels), ago_train/cli.py (train, eval, open-world),
ago_train/experiments/cli.py (experiments run|report|list), ago_export/cli.py (export).
`VERB_MODULES` names them as data, like a package's entry points: this module imports none of them
at import time, and nothing in ago_runtime imports ago_train or ago_export (tests/test_architecture.py).
The app imports them the first time it is turned into a click command (running `ago`, `--help`,
typer's CliRunner); a verb module imports nothing heavy (torch is imported inside the command), so
`ago infer` works on a runtime-only install and `ago train` says which extra to install when torch
is missing (`ago_runtime.errors.require_torch`). A package that is not installed just has no verbs.

Every failure caused by the user's input leaves through `exit_code_for` (used by `main`):
- AgoInputError (a file, a config, an option value) and MissingExtra: `error: <file or option>: <problem>`;
- click's usage errors (an unknown option, a value of the wrong type, a missing option, a value
  outside an option's range): `error: <option>: <problem> (see 'ago VERB --help')`;
- an OSError that names a file (PermissionError on an output folder, a full disk ...):
  `error: <file>: <strerror>`;
each as ONE line on stderr and exit code 2. Anything else is a bug and keeps its traceback.
Warnings print as one line each (`warning: <message>`, `ago_runtime.errors.one_line_warnings`).

Usage errors are recognised by class name through typer's own exception classes, because typer
>= 0.26 carries its own copy of click (`typer._click`) while older typer uses the standalone click:
`click_exception_classes()` finds both.
"""

from __future__ import annotations

import importlib
import sys

import typer

from ago_runtime.errors import AgoInputError, MissingExtra, one_line, one_line_warnings, require_torch

__all__ = ["app", "run", "main", "exit_code_for", "click_exception_classes", "MissingExtra", "require_torch"]

# Each module defines `register(app)`. Order = order in `ago --help` (typer lists groups after commands).
VERB_MODULES = (
    "ago_runtime.predict.cli",    # ago infer, ago demo, ago retrieve
    "ago_runtime.vocab.cli",      # ago prompts build|show
    "ago_train.text.cli",         # ago prompts export-encoder|noise
    "ago_runtime.pictures.cli",   # ago show
    "ago_runtime.scoring.cli",    # ago metric
    "ago_train.synth.cli",        # ago synth
    "ago_train.pseudo.cli",       # ago pseudo-labels
    "ago_train.cli",              # ago train, ago eval, ago open-world
    "ago_train.experiments.cli",  # ago experiments run|report|list
    "ago_export.cli",             # ago export
)


def _verbs_first(name: str) -> property:
    """An attribute typer reads to build the click group, that loads the verb modules first."""
    def read(self):
        self._load_verbs()
        return self.__dict__["_" + name]

    def write(self, value):
        self.__dict__["_" + name] = value

    return property(read, write)


class VerbTable(typer.Typer):
    """A Typer whose verbs come from `verb_modules`, registered the first time its commands are read
    (typer.main.get_command reads `registered_commands` / `registered_groups` to build the click group)."""

    def __init__(self, *args, verb_modules: tuple[str, ...] = (), **kwargs):
        self._verb_modules = tuple(verb_modules)
        self._verbs_loaded = False
        super().__init__(*args, **kwargs)

    def _load_verbs(self) -> None:
        if self._verbs_loaded:
            return
        self._verbs_loaded = True
        for name in self._verb_modules:
            try:
                module = importlib.import_module(name)
            except ModuleNotFoundError as e:  # a part not installed (or not written yet) just has no verbs
                if e.name is not None and name.startswith(e.name):
                    continue
                raise
            module.register(self)

    registered_commands = _verbs_first("registered_commands")
    registered_groups = _verbs_first("registered_groups")


app = VerbTable(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                help="ago: open-world 3D semantic occupancy from surround cameras (AGO, ICCV 2025).",
                verb_modules=VERB_MODULES)


# ------------------------------------------------------------------------------------ errors
def _classes_named(name: str) -> tuple[type, ...]:
    """The exception classes called `name` in the MRO of typer's BadParameter / Exit / Abort, and in the
    standalone click when it is installed (older typer raises click's own classes)."""
    found = []
    roots = [typer.BadParameter, getattr(typer, "Exit", None), getattr(typer, "Abort", None)]
    try:
        import click.exceptions as ce

        roots += [ce.BadParameter, ce.Exit, ce.Abort]
    except ImportError:
        pass
    for root in roots:
        for cls in getattr(root, "__mro__", ()):
            if cls.__name__ == name and cls not in found:
                found.append(cls)
    return tuple(found)


def click_exception_classes() -> dict[str, tuple[type, ...]]:
    """{"ClickException", "Abort", "Exit"} -> the classes of that name typer (and click) raise."""
    return {name: _classes_named(name) for name in ("ClickException", "Abort", "Exit")}


def _param_name(param) -> str | None:
    """'--scenes' for an option (its first long name), 'PROMPT_FILE' for an argument."""
    if param is None:
        return None
    opts = list(getattr(param, "opts", None) or [])
    if getattr(param, "param_type_name", "") == "argument" or not opts:
        return str(getattr(param, "human_readable_name", None) or getattr(param, "name", "") or "").upper() or None
    longs = [o for o in opts if o.startswith("--")]
    return (longs or opts)[0]


def usage_error_line(e: BaseException) -> str:
    """One line `<option or command>: <problem> (see '<command> --help')` for a click usage error."""
    ctx = getattr(e, "ctx", None)
    command = getattr(ctx, "command_path", None) or "ago"
    name = _param_name(getattr(e, "param", None))
    kind = type(e).__name__
    message = str(getattr(e, "message", "") or "")
    if kind == "NoSuchOption":
        name = getattr(e, "option_name", None) or name
        message = "no such option"
        possible = list(getattr(e, "possibilities", None) or [])
        if possible:
            message += f" (did you mean {', '.join(sorted(possible))}?)"
    elif kind == "MissingParameter":
        what = "argument" if getattr(getattr(e, "param", None), "param_type_name", "") == "argument" else "option"
        message = f"missing {what}" + (f" ({message})" if message else "")
    elif kind in ("BadOptionUsage",):
        name = getattr(e, "option_name", None) or name
    elif not message:
        message = e.format_message() if hasattr(e, "format_message") else str(e)
    return one_line(f"{name or command}: {message} (see '{command} --help')")


def exit_code_for(e: BaseException) -> int:
    """Print the one error line for `e` on stderr and give the exit code; re-raise what is not bad input."""
    classes = click_exception_classes()
    if isinstance(e, (AgoInputError, MissingExtra)):
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2
    if isinstance(e, classes["ClickException"]):
        if type(e).__name__ == "NoArgsIsHelpError":   # `ago` / `ago prompts` alone: the help text
            print(e.format_message(), file=sys.stdout)
            return 2
        if type(e).__name__ == "FileError":
            print(f"error: {one_line(e.format_message())}", file=sys.stderr)
            return 2
        print(f"error: {usage_error_line(e)}", file=sys.stderr)
        return 2
    if isinstance(e, classes["Abort"]) or isinstance(e, KeyboardInterrupt):
        print("error: interrupted", file=sys.stderr)
        return 130
    if isinstance(e, OSError) and getattr(e, "filename", None):
        print(f"error: {e.filename}: {one_line(e.strerror or e)}", file=sys.stderr)
        return 2
    raise e


def empty_option(args: list[str]) -> str | None:
    """The first option of `args` given an empty (or all-blank) value, e.g. `--out ''` (which would mean the
    working folder), else None. Found on the verb's click command: options that take a value (not flags)."""
    import typer.main

    cmd = typer.main.get_command(app)
    i = 0
    while i < len(args) and args[i] in (getattr(cmd, "commands", None) or {}):
        cmd = cmd.commands[args[i]]
        i += 1
    takes_value = {o: not p.is_flag for p in getattr(cmd, "params", []) if p.param_type_name == "option"
                   for o in list(p.opts) + list(p.secondary_opts)}
    while i < len(args):
        a = args[i]
        if a == "--":
            break
        name, value = a.split("=", 1) if a.startswith("--") and "=" in a else (a, None)
        if takes_value.get(name):
            if value is None:
                i += 1
                value = args[i] if i < len(args) else None
            if value is not None and not value.strip():
                return name
        i += 1
    return None


def run(argv: list[str] | None = None) -> int:
    """Run `ago` with `argv` (default sys.argv[1:]); gives the exit code (errors already printed)."""
    one_line_warnings()
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        empty = empty_option(args)
        if empty is not None:   # `--out ''` would write into the working folder: refused for every option
            raise AgoInputError(empty, "is empty")
        rc = app(args=args, prog_name="ago", standalone_mode=False)
    except SystemExit:
        raise
    except BaseException as e:  # noqa: BLE001 - every exit goes through exit_code_for
        return exit_code_for(e)
    return rc if isinstance(rc, int) else 0   # click returns Exit's code (e.g. 0 after --help)


def main() -> None:
    rc = run()
    if rc:
        sys.exit(rc)


if __name__ == "__main__":
    main()
