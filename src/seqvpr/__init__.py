"""seqvpr: sequence-based visual place recognition.

The data flow is: traversals (frames with descriptors and positions) -> descriptors -> transform or sequence
descriptor -> matching (one kernel) or retrieval -> predictions -> evaluation -> report. See README.md
("Architecture") for which package owns each step, ``seqvpr.pipeline`` for the stage functions and
``seqvpr.methods.run_method`` for every method by name.
"""

from seqvpr.errors import SeqvprError

__version__ = "0.1.0"
__all__ = ["SeqvprError", "__version__"]
