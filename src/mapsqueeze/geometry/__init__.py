"""Geometric operations shared by data, model and metrics: grids, voxels, normals (numpy/scipy)."""
