"""Shared point-cloud numerics used by every product: ICP (and, one implementation each, voxel
thinning, covariance features, clustering and robust shape fitting). Points are (N, 3) float64
arrays in metres, in whatever frame the caller works in."""
