"""One exception type for bad input; the CLI turns it into a one-line message and exit 2."""


class AgoInputError(ValueError):
    """Bad user input (a file, a config, a calibration). The message names the file and the problem."""

    def __init__(self, path, problem: str):
        self.path = str(path) if path is not None else None
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)
