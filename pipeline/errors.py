"""Errors a user can act on. The CLI prints them as one line and exits with status 2.

Every error that names a bad input (file, frame, design, calibration, option) derives from
:class:`UserError`; anything else escaping the CLI is a bug.
"""


class UserError(Exception):
    """Base for errors caused by the user's input (bad file, unknown name, wrong option)."""


class SourceError(UserError):
    """A frame source cannot be opened or delivers frames of the wrong size, channels or type."""
