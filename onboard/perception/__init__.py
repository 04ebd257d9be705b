"""Perception geometry: depth images to a world-frame occupancy grid to convex sets.

Pipeline (thesis 3336): depth image + camera pose -> point cloud (``pointcloud``) ->
traversable / occupied labels (``segmentation``, pluggable) -> vertical binning into a
fused, decaying occupancy grid (``occupancy``) -> convex free polygons (Algorithm 4,
``decomposition``) or convex obstacles (``obstacles``). Pure: no I/O, no clocks.
"""
