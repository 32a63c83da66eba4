"""User-facing errors.

Every problem a user can cause (a bad file, parameter, value or environment) is raised as an
:class:`EloError` whose message is one line naming what is wrong and what is allowed. The CLI prints
that line and exits with status 2; it never shows a traceback for an ``EloError``.
"""


class EloError(Exception):
    """A problem with user input or the environment, explained in one line."""


class EloEnvironmentError(EloError, RuntimeError):
    """The machine cannot run the renderer (missing or too old LLVM, no CUDA, ...)."""


class EloInputError(EloError, ValueError):
    """A parameter, file or value given by the user is invalid."""
