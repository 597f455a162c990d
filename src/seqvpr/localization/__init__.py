"""Online localisation over a saved map: ``Localizer`` (one frame at a time), replay of recorded traversals and
calibrated thresholds."""

from seqvpr.localization.localizer import Estimate, Localizer, LocalizerSettings

__all__ = ["Estimate", "Localizer", "LocalizerSettings"]
