"""The exceptions a user sees as a one-line message and a non-zero exit."""

import signal


class UserError(Exception):
    """Bad input or a refused action, reported as `colmap-ext: error: <message>`."""


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread so that every clean-up runs; the
    command exits with 128 + the signal's number."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
