"""The one exception type users see for bad input."""


class FwdfitError(ValueError):
    """Bad user input (scene, profile table, command-line option): a one-line message.

    The command line prints the message and exits with status 1; library callers
    catch it as a ``ValueError``.
    """
