"""Geometry shared by several layers: unit quaternions on S3 (ch. 4.1), Bezier curves and
their control-point algebra (ch. 6.1), convex polygons. Assumes only the contracts; guarantees
pure functions of their arguments, with units and frames in each docstring."""
