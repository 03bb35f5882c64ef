"""The one exception a user sees as a one-line message and a non-zero exit."""


class UserError(Exception):
    """Bad input or a refused action, reported as `colmap-ext: error: <message>`."""
