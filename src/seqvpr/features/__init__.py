"""From images to descriptors: weight-free patch-normalised thumbnails (learned backbones come later)."""

from seqvpr.features.patchnorm import PatchNormConfig, patch_normalize, patchnorm_descriptors

__all__ = ["PatchNormConfig", "patch_normalize", "patchnorm_descriptors"]
