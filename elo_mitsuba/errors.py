"""User-facing errors.

Every problem a user can cause (a bad file, parameter, value or environment) is raised as an
:class:`EloError` whose message is one line naming what is wrong and what is allowed. The CLI prints
that line and exits with status 2; it never shows a traceback for an ``EloError``.
"""


class EloError(Exception):
    """A problem with user input or the environment, explained in one line.

    Examples
    --------
    >>> import elo_mitsuba as em
    >>> try:
    ...     em.load_scene("no_such_scene")
    ... except em.EloError as exc:
    ...     print(type(exc).__name__, "|", len(str(exc).splitlines()))
    EloInputError | 1
    """


class EloEnvironmentError(EloError, RuntimeError):
    """The machine cannot run the renderer (missing or too old LLVM, no CUDA, ...).

    Examples
    --------
    >>> from elo_mitsuba import EloEnvironmentError, EloError
    >>> issubclass(EloEnvironmentError, EloError), issubclass(EloEnvironmentError, RuntimeError)
    (True, True)
    """


class EloInputError(EloError, ValueError):
    """A parameter, file or value given by the user is invalid.

    Examples
    --------
    >>> import elo_mitsuba as em
    >>> try:
    ...     em.load_scene("flat_plate", colour=3)
    ... except em.EloInputError as exc:
    ...     print(exc)
    /...flat_plate.xml: parameter 'colour' is not declared by this scene (it declares: ...)
    >>> issubclass(em.EloInputError, ValueError)
    True
    """
