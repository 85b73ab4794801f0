"""The ground floor: geometry every other room builds on, on numpy, scipy, numba and torch tensors only.

`validation` (the point-cloud check every entry applies), `bounds`, `voxel` (voxel filter and keys), `tiling`
(the codec's grid of 40 x 40 x 15 m tiles), `grid` (grid subsampling and capped radius neighbours of the encoder),
`morton` (Morton order, evenly spread subsets), `resample` (exact point counts), `normals` (PCA normals),
`threads` (the shared thread pool of the compiled kernels). Imports only `mapsqueeze.errors` from the package.
"""
