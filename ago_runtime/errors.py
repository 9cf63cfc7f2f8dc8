"""The errors every verb shares: bad input (AgoInputError), a missing extra (MissingExtra, require_torch),
and the one-line form the CLI prints them and warnings in (ago_runtime/cli.py turns them into exit 2)."""


class AgoInputError(ValueError):
    """Bad user input (a file, a config, a calibration). The message names the file and the problem."""

    def __init__(self, path, problem: str):
        self.path = str(path) if path is not None else None
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class AgoNote(UserWarning):
    """Information a user should see once, e.g. which shipped file a name stood for. The CLI prints it as
    `note: <message>` on stdout (`one_line_warnings`); from Python it is a warning of this class."""


class MissingExtra(RuntimeError):
    """A verb needs an optional part (torch: the training extra) that is not installed."""


def require_torch(verb: str) -> None:
    """Call at the top of a verb that needs torch: a clear message instead of an ImportError trace."""
    import importlib.util

    if importlib.util.find_spec("torch") is None:  # look, don't import: the runtime never loads torch
        raise MissingExtra(f"`ago {verb}` needs the training extra: pip install -e '.[train]' "
                           "(and scripts/setup.sh for the bundled weights)")


def refuse_unused(given: dict, input_kind: str) -> None:
    """Options that do not apply to the input given are refused, not ignored: `given` maps an option's name
    to its value (None when not given); the first given one is AgoInputError(option, "does not apply to ...")."""
    for option, value in given.items():
        if value is not None:
            raise AgoInputError(option, f"does not apply to {input_kind}")


def one_line(text) -> str:
    """`text` with every run of white space (newlines included) folded to one space."""
    return " ".join(str(text).split())


def one_line_warnings() -> None:
    """Show warnings as `warning: <message>`, one line each, on stderr, and AgoNote as `note: <message>` on
    stdout (the CLI's warning path: stderr keeps only warnings and the one error line)."""
    import sys
    import warnings

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, AgoNote):
            print(f"note: {one_line(message)}", file=sys.stdout)
        else:
            print(f"warning: {one_line(message)}", file=sys.stderr)

    warnings.showwarning = show
