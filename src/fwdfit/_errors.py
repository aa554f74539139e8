"""The one exception type users see for bad input, and the warning for a model less exact than asked."""


class FwdfitError(ValueError):
    """Bad user input (scene, profile table, command-line option): a one-line message.

    The command line prints the message and exits with status 1; library callers
    catch it as a ``ValueError``.
    """


class ModelWarning(UserWarning):
    """The model of a scene is less exact than its accuracy asks (a physics combination
    not modelled yet); the command line prints it as one ``warning:`` line."""
