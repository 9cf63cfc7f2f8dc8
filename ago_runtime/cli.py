"""The `ago` command line (typer): the table of verb modules, the app built from it, and the one error path.

Verbs live next to what they drive, each module defining `register(app)`:
ago_runtime/predict/cli.py (infer, demo, retrieve), ago_runtime/vocab/cli.py (prompts build|show),
ago_runtime/pictures/cli.py (show), ago_runtime/scoring/cli.py (metric), and in the training
packages ago_train/text/cli.py (prompts export-encoder|noise), ago_train/synth/cli.py (synth),
ago_train/pseudo/cli.py (pseudo-labels, seen-gt), ago_train/cli.py (train, calibrate, eval, open-world),
ago_train/experiments/cli.py (experiments run|report|list), ago_export/cli.py (export).
`VERB_MODULES` names them as data, verb -> modules, like a package's entry points: nothing in
ago_runtime imports ago_train or ago_export by name (tests/test_architecture.py). `build_app(verb)`
makes a typer app holding that verb's modules only (`ago infer` imports no training verb module),
`build_app()` one with every verb (`ago --help`, an unknown verb; `app`, read from this module, is
such an app, made when first read). A module of a package that is not installed is left out, so a
runtime-only install just has no training verbs. A verb module imports nothing heavy (torch is
imported inside the command), and `ago train` without torch says which extra to install
(`ago_runtime.errors.require_torch`).

Every failure caused by the user's input leaves through `exit_code_for` (used by `run`):
- AgoInputError (a file, a config, an option value) and MissingExtra: `error: <file or option>: <problem>`;
- click's usage errors (an unknown option, a value of the wrong type, a missing option, a value
  outside an option's range): `error: <option>: <problem> (see 'ago VERB --help')`;
- an OSError that names a file (PermissionError on an output folder, a full disk ...):
  `error: <file>: <strerror>`;
each as ONE line on stderr and exit code 2. Anything else is a bug and keeps its traceback.
Warnings print as one line each (`warning: <message>`, notes as `note: <message>`;
`ago_runtime.errors.one_line_warnings`). `ago` or `ago prompts` alone print the help, exit 2.

The usage errors are the exception classes of the click that typer runs on: typer >= 0.26 carries its
own copy (`typer._click`), older typer uses click itself. `click_exceptions()` is that module, found
from `typer.BadParameter` (public in every typer), so only that one copy is consulted.
"""

from __future__ import annotations

import importlib
import sys
from types import ModuleType

import typer
import typer.main

from ago_runtime.errors import AgoInputError, MissingExtra, one_line, one_line_warnings

__all__ = ["VERB_MODULES", "build_app", "run", "main", "exit_code_for"]

# verb -> the modules that define it (each module has `register(app)`). Order = order in `ago --help`
# (typer lists groups after commands). `prompts` is a group two packages add verbs to.
VERB_MODULES: dict[str, tuple[str, ...]] = {
    "infer": ("ago_runtime.predict.cli",),
    "demo": ("ago_runtime.predict.cli",),
    "retrieve": ("ago_runtime.predict.cli",),
    "prompts": ("ago_runtime.vocab.cli", "ago_train.text.cli"),   # build|show; export-encoder|noise
    "show": ("ago_runtime.pictures.cli",),
    "metric": ("ago_runtime.scoring.cli",),
    "synth": ("ago_train.synth.cli",),
    "pseudo-labels": ("ago_train.pseudo.cli",),
    "seen-gt": ("ago_train.pseudo.cli",),
    "train": ("ago_train.cli",),
    "train-real": ("ago_train.cli",),
    "calibrate": ("ago_train.cli",),
    "eval": ("ago_train.cli",),
    "open-world": ("ago_train.cli",),
    "experiments": ("ago_train.experiments.cli",),
    "export": ("ago_export.cli",),
}

HELP = "ago: open-world 3D semantic occupancy from surround cameras (AGO, ICCV 2025)."


def _import_verb_module(name: str) -> ModuleType | None:
    """The verb module `name`, or None when its package is not installed (a runtime-only install)."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        if e.name is not None and name.startswith(e.name):
            return None
        raise


def _group_callback() -> None:
    """ago: open-world 3D semantic occupancy from surround cameras (AGO, ICCV 2025)."""


def build_app(verb: str | None = None) -> typer.Typer:
    """A typer app with the modules of `verb` registered (a name of VERB_MODULES), or every verb's
    (None, or a name that is not a verb: click then reports it)."""
    modules = VERB_MODULES.get(verb) if verb is not None else None
    if modules is None:
        modules = tuple(dict.fromkeys(m for ms in VERB_MODULES.values() for m in ms))
    app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, help=HELP,
                      callback=_group_callback)   # a callback keeps one verb a group: `ago show X`, not `ago X`
    for name in modules:
        module = _import_verb_module(name)
        if module is not None:
            module.register(app)
    return app


def __getattr__(name: str):
    """`ago_runtime.cli.app`: an app with every verb (typer's CliRunner, `typer.main.get_command`), made
    when first read, so that importing this module imports no verb module."""
    if name == "app":
        app = build_app()
        globals()["app"] = app
        return app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ------------------------------------------------------------------------------------ errors
def click_exceptions() -> ModuleType:
    """The module of the exception classes the click under typer raises (`typer._click.exceptions` for
    typer >= 0.26, `click.exceptions` before), found from the public `typer.BadParameter`."""
    return sys.modules[typer.BadParameter.__module__]


def _param_name(param) -> str | None:
    """'--scenes' for an option (its first long name), 'PROMPT_FILE' for an argument."""
    if param is None:
        return None
    opts = list(param.opts or [])
    if param.param_type_name == "argument" or not opts:
        return str(getattr(param, "human_readable_name", None) or param.name or "").upper() or None
    longs = [o for o in opts if o.startswith("--")]
    return (longs or opts)[0]


def usage_error_line(e: BaseException) -> str:
    """One line `<option or command>: <problem> (see '<command> --help')` for a click usage error."""
    ce = click_exceptions()
    command = e.ctx.command_path if getattr(e, "ctx", None) is not None else "ago"
    name = _param_name(getattr(e, "param", None))
    message = str(getattr(e, "message", "") or "")
    if isinstance(e, ce.NoSuchOption):
        name = e.option_name
        message = "no such option"
        if e.possibilities:
            message += f" (did you mean {', '.join(sorted(e.possibilities))}?)"
    elif isinstance(e, ce.MissingParameter):
        what = "argument" if e.param is not None and e.param.param_type_name == "argument" else "option"
        message = f"missing {what}" + (f" ({message})" if message else "")
    elif isinstance(e, ce.BadOptionUsage):
        name = e.option_name or name
    if not message:
        message = e.format_message()
    return one_line(f"{name or command}: {message} (see '{command} --help')")


def exit_code_for(e: BaseException) -> int:
    """Print the one error line for `e` on stderr and give the exit code; re-raise what is not bad input."""
    ce = click_exceptions()
    if isinstance(e, (AgoInputError, MissingExtra)):
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2
    if isinstance(e, ce.UsageError):
        print(f"error: {usage_error_line(e)}", file=sys.stderr)
        return 2
    if isinstance(e, ce.ClickException):   # click's other errors (a file it could not open)
        print(f"error: {one_line(e.format_message())}", file=sys.stderr)
        return 2
    if isinstance(e, (typer.Abort, KeyboardInterrupt)):
        print("error: interrupted", file=sys.stderr)
        return 130
    if isinstance(e, OSError) and getattr(e, "filename", None):
        print(f"error: {e.filename}: {one_line(e.strerror or e)}", file=sys.stderr)
        return 2
    raise e


def _named_command(command, args: list[str]):
    """(the click command `args` name: the group, a sub-group or a verb; the index of the first other argument)."""
    i = 0
    while i < len(args) and hasattr(command, "commands") and args[i] in command.commands:
        command = command.commands[args[i]]
        i += 1
    return command, i


def empty_option(command, args: list[str]) -> str | None:
    """The first option of `args` given an empty (or all-blank) value, e.g. `--out ''` (which would mean the
    working folder), else None. Found on the verb's click command: options that take a value (not flags)."""
    cmd, i = _named_command(command, args)
    takes_value = {o: not p.is_flag for p in cmd.params if p.param_type_name == "option"
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
        command = typer.main.get_command(build_app(args[0] if args else None))
        named, i = _named_command(command, args)
        if i == len(args) and hasattr(named, "commands"):   # `ago`, `ago prompts`: a group alone, its help
            command.main(args=args + ["--help"], prog_name="ago", standalone_mode=False)
            return 2
        empty = empty_option(command, args)
        if empty is not None:   # `--out ''` would write into the working folder: refused for every option
            raise AgoInputError(empty, "is empty")
        rc = command.main(args=args, prog_name="ago", standalone_mode=False)
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
