"""Geometry tools every layer shares: ray casting against meshes (Embree), camera projection,
vertex normals and connected components. No igavatar imports beyond errors."""
