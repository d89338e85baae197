"""Synthetic data for the Intrinsic Autoencoder (Alhaija et al., 3DV 2020).

Only `scene`, `render` (and the PBR/importer modules) import bpy; the dataset format
(`dataset`, `conversions`) is shared with `train` and `eval` and stays bpy-free.
"""
