"""``python -m seqvpr.cli``: the same as the ``seqvpr`` command."""

from seqvpr.cli import main

main()
