"""The one exception type users see: a one-line message that names the file or field at fault."""


class SeqvprError(ValueError):
    """Bad input or an impossible request; the CLI prints the message on one line and exits non-zero."""


class SeqvprWarning(UserWarning):
    """Input that works but is suspect (a ground-truth file naming frames the traversal lacks): the CLI prints it as
    one ``seqvpr: warning:`` line and goes on."""
