"""The `ago` command line (typer): the table of verb modules, the app built from it, and the one error path.

Verbs live next to what they drive, each module defining `register(app)`:
ago_runtime/predict/cli.py (infer, demo, retrieve, choose-threshold), ago_runtime/vocab/cli.py (prompts build|show),
ago_runtime/pictures/cli.py (show), ago_runtime/scoring/cli.py (metric), and in the training
packages ago_train/text/cli.py (prompts export-encoder|noise), ago_train/synth/cli.py (synth),
ago_train/vlm/cli.py (vlm-files), ago_train/pseudo/cli.py (pseudo-labels, seen-gt), ago_train/cli.py (train, calibrate, eval, open-world),
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
- a usage error of the click typer runs on (an unknown option, a value of the wrong type or not one of an
  enum's values, a missing option, a value outside an option's range, an empty value):
  `error: <option>: <problem> (see 'ago VERB --help')`;
- an OSError that names a file (PermissionError on an output folder, a full disk ...):
  `error: <file>: <strerror>`;
each as ONE line on stderr and exit code 2. Anything else is a bug and keeps its traceback.
Warnings print as one line each (`warning: <message>`, notes as `note: <message>`;
`ago_runtime.errors.one_line_warnings`). `ago` or `ago prompts` alone print the help, exit 2 (`verb_group`).

Only typer's public API is used, the same on every typer of the pinned range (pyproject.toml; typer >= 0.26
carries its own copy of click, older typer runs on click itself): the app is run through
`typer.main.get_command(app).main(..., standalone_mode=False)`; errors are told apart by the classes typer
exports (`typer.BadParameter`, `typer.Abort`, `typer.Exit`, and `CLICK_ERROR`: the root of typer.BadParameter's
exception classes, the base of every error its click raises) and the attributes click documents
on them (`param`, `ctx`, `option_name`, `possibilities`, `param_type`); options with a fixed set of values are
typed as Enums, so their help and their check come from the Enum; every verb's command class is
`CheckedValues`, which refuses an empty value (`--out ''` would mean the working folder), a control character
or an over-long value (`value_problem`) option by option, right after click parsed them.
"""

from __future__ import annotations

import importlib
import sys
from types import ModuleType

import typer
import typer.core
import typer.main

from ago_runtime.errors import AgoInputError, MissingExtra, one_line, one_line_warnings
from ago_runtime.progress import quiet_library_bars

__all__ = ["VERB_MODULES", "build_app", "verb_group", "run", "main", "exit_code_for"]

# verb -> the modules that define it (each module has `register(app)`). Order = order in `ago --help`
# (typer lists groups after commands). `prompts` is a group two packages add verbs to.
VERB_MODULES: dict[str, tuple[str, ...]] = {
    "infer": ("ago_runtime.predict.cli",),
    "demo": ("ago_runtime.predict.cli",),
    "retrieve": ("ago_runtime.predict.cli",),
    "choose-threshold": ("ago_runtime.predict.cli",),
    "prompts": ("ago_runtime.vocab.cli", "ago_train.text.cli"),   # build|show; export-encoder|noise
    "show": ("ago_runtime.pictures.cli",),
    "metric": ("ago_runtime.scoring.cli",),
    "synth": ("ago_train.synth.cli",),
    "vlm-files": ("ago_train.vlm.cli",),
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


def _help_when_alone(ctx: typer.Context) -> None:
    """A group given no verb (`ago`, `ago prompts`): its help on stdout, exit code 2."""
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())
        raise typer.Exit(2)


def verb_group(help: str) -> typer.Typer:
    """A group of verbs (`ago prompts`, `ago experiments`): alone, it prints its help and exits 2."""
    return typer.Typer(help=help, invoke_without_command=True, callback=_help_when_alone)


MAX_OPTION_CHARS = 4096      # any option or argument value (a path: Linux's PATH_MAX)
MAX_SET_CHARS = 100_000      # a --set KEY=VALUE (ago_train/train_config.py bounds the value alike)
# options whose value is a name or a note, not a path: bounded as a phrase (ago_runtime.vocab.prompts.MAX_PHRASE_CHARS)
NAME_OPTIONS = ("--phrase", "--template", "--card-note", "--sample", "--split", "--eval-split", "--subset", "--stage",
                "--profile", "--identifier", "--device", "--precision", "--picture", "--view", "--layout", "--rig",
                "--shard", "--seeds", "--readout", "--readout-grid", "--grid", "--image-size", "--segmenter",
                "--embedder", "--ray-origin", "--int8-float")


def value_problem(name: str, value: str) -> str | None:
    """What is wrong with one option or argument value, else None: empty or all blank (`--out ''` would mean the
    working folder), a control character (a NUL, an escape; `--set` may hold the tabs and newlines of JSON), more
    than MAX_OPTION_CHARS characters (--set: MAX_SET_CHARS), a name or note (NAME_OPTIONS) of more than
    MAX_PHRASE_CHARS."""
    from ago_runtime.vocab.prompts import MAX_PHRASE_CHARS

    if not value.strip():
        return "is empty"
    allowed = "\t\n\r" if name == "--set" else ""
    bad = next((c for c in value if (ord(c) < 32 or 127 <= ord(c) < 160) and c not in allowed), None)
    if bad is not None:
        return f"holds the control character {bad!r}"
    limit = MAX_SET_CHARS if name == "--set" else MAX_PHRASE_CHARS if name in NAME_OPTIONS else MAX_OPTION_CHARS
    if len(value) > limit:
        return f"is {len(value)} characters long (at most {limit})"
    return None


class CheckedValues(typer.core.TyperCommand):
    """Every verb's command class (set by `build_app`): each option and argument value is checked by
    `value_problem` (empty, control characters, length bounds), naming the option, before click converts it
    (a Path of '' is '.') and before any work. The values are the ones this command's own click parser
    (`make_parser`) reads, so an option is found exactly as click finds it (`--out=`, `-o ''`, a repeated option)."""

    def parse_args(self, ctx, args):
        try:
            raw, _, _ = self.make_parser(ctx).parse_args(args=list(args))
        except Exception:  # noqa: BLE001 - a usage error: click's own parse below reports it
            raw = {}
        for param in self.get_params(ctx):
            if param.param_type_name not in ("option", "argument") or param.name not in raw:
                continue
            value = raw[param.name]
            name = _param_name(param)
            for v in value if isinstance(value, (list, tuple)) else [value]:
                problem = value_problem(name, v) if isinstance(v, str) else None
                if problem is not None:
                    raise AgoInputError(name, problem)
        return super().parse_args(ctx, args)


def _verb_commands(app: typer.Typer):
    """The command records of `app` and of its groups (typer's registration, before any click command exists)."""
    yield from app.registered_commands
    for group in app.registered_groups:
        yield from _verb_commands(group.typer_instance)


def build_app(verb: str | None = None) -> typer.Typer:
    """A typer app with the modules of `verb` registered (a name of VERB_MODULES), or every verb's
    (None, or a name that is not a verb: click then reports it)."""
    modules = VERB_MODULES.get(verb) if verb is not None else None
    if modules is None:
        modules = tuple(dict.fromkeys(m for ms in VERB_MODULES.values() for m in ms))
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, help=HELP, invoke_without_command=True,
                      callback=_help_when_alone)   # a callback keeps one verb a group: `ago show X`, not `ago X`
    for name in modules:
        module = _import_verb_module(name)
        if module is not None:
            module.register(app)
    for command in _verb_commands(app):   # typer's default command class (a verb asking for its own keeps it)
        if command.cls in (None, typer.core.TyperCommand):
            command.cls = CheckedValues
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
# The root of the exceptions the click under typer raises: the ancestor of the public `typer.BadParameter` just
# below Exception (click's ClickException on typer 0.18, typer's own copy of it on 0.26, typer.TyperException on
# 0.29), so the handler never names a module of typer's own click.
CLICK_ERROR: type[Exception] = typer.BadParameter.__mro__[typer.BadParameter.__mro__.index(Exception) - 1]

USAGE_EXIT_CODE = 2   # click's UsageError (and each subclass: BadParameter, NoSuchOption ...) exits with 2


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
    command = e.ctx.command_path if getattr(e, "ctx", None) is not None else "ago"
    name = _param_name(getattr(e, "param", None))
    message = str(getattr(e, "message", "") or "")
    if getattr(e, "option_name", None) and hasattr(e, "possibilities"):   # an unknown option (NoSuchOption)
        name = e.option_name
        message = "no such option"
        if e.possibilities:
            message += f" (did you mean {', '.join(sorted(e.possibilities))}?)"
    elif isinstance(e, typer.BadParameter) and hasattr(e, "param_type"):   # a missing option or argument
        what = "argument" if e.param is not None and e.param.param_type_name == "argument" else "option"
        message = f"missing {what}" + (f" ({message})" if message else "")
    elif getattr(e, "option_name", None):   # an option used wrongly (BadOptionUsage)
        name = e.option_name
    if not message:
        message = e.format_message()
    message = message.removeprefix("Value error, ")   # how typer 0.29 words a failed Enum check (0.26 does not)
    return one_line(f"{name or command}: {message} (see '{command} --help')")


def exit_code_for(e: BaseException) -> int:
    """Print the one error line for `e` on stderr and give the exit code; re-raise what is not bad input."""
    if isinstance(e, (AgoInputError, MissingExtra)):
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2
    if isinstance(e, CLICK_ERROR) and getattr(e, "exit_code", None) == USAGE_EXIT_CODE:
        print(f"error: {usage_error_line(e)}", file=sys.stderr)
        return 2
    if isinstance(e, CLICK_ERROR):   # click's other errors (a file it could not open)
        print(f"error: {one_line(e.format_message())}", file=sys.stderr)
        return 2
    if isinstance(e, (typer.Abort, KeyboardInterrupt)):
        print("error: interrupted", file=sys.stderr)
        return 130
    if isinstance(e, OSError) and getattr(e, "filename", None):
        print(f"error: {e.filename}: {one_line(e.strerror or e)}", file=sys.stderr)
        return 2
    raise e


def run(argv: list[str] | None = None) -> int:
    """Run `ago` with `argv` (default sys.argv[1:]); gives the exit code (errors already printed)."""
    one_line_warnings()
    quiet_library_bars()   # no bars (ago's or a library's) in a redirected stderr
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        command = typer.main.get_command(build_app(args[0] if args else None))
        rc = command.main(args=args, prog_name="ago", standalone_mode=False)
    except SystemExit:
        raise
    except BaseException as e:  # noqa: BLE001 - every exit goes through exit_code_for
        return exit_code_for(e)
    return rc if isinstance(rc, int) else 0   # click returns Exit's code (e.g. 0 after --help, 2 for a group alone)


def main() -> None:
    rc = run()
    if rc:
        sys.exit(rc)


if __name__ == "__main__":
    main()
