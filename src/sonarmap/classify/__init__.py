"""Pixel classifiers: thresholds, local MAP (eq. 12-14), CFAR and MRF segmentation."""
