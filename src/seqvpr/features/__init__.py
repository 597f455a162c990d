"""From images to descriptors: patch-normalised thumbnails, backbones with GeM or NetVLAD pooling, PCA-whitening."""
