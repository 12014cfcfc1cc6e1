"""The one exception type users see for bad input."""

import os


class InputError(ValueError):
    """Bad user input: a file, a value or a flag that cannot be used as given.

    The message names the file (or flag), the problem and what was expected, so the CLI can print
    it as one line and exit with status 2.
    """

    def __init__(self, source: str | os.PathLike, problem: str, expected: str | None = None):
        self.source = str(source)
        self.problem = problem
        self.expected = expected
        msg = f"{self.source}: {problem}"
        if expected:
            msg += f" (expected {expected})"
        super().__init__(msg)
