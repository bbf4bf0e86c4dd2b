"""Input exposures.

Our exposure files, survey multi-extension layouts and their readers, manifests and PSF
model files.
"""
