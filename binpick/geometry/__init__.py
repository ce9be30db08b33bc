"""Geometry kernels: rigid transforms, symmetries, planes, normals, neighbour search."""
