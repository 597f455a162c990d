"""seqvpr: sequence-based visual place recognition.

The data flow is: traversals (frames with descriptors and positions) -> sequence matching with one kernel
-> predictions -> evaluation.  See README.md for the command line and ``seqvpr.pipeline`` for the Python entry
points.
"""

from seqvpr.errors import SeqvprError

__version__ = "0.1.0"
__all__ = ["SeqvprError", "__version__"]
