"""Intensity statistics: discrete mixture components, fits (LSQ and EM), model selection, ROC."""
