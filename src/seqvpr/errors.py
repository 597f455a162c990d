"""The one exception type users see: a one-line message that names the file or field at fault."""


class SeqvprError(ValueError):
    """Bad input or an impossible request; the CLI prints the message on one line and exits non-zero."""
