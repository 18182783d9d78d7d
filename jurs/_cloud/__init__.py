"""Host-side geometry of point clouds: neighbours, spacing, noise, features, and normals
estimated and oriented."""
