"""The overhead camera of the indoor lab (thesis 7.2, Fig. 7.7): a camera looking down at the floor
(any UVC camera through ``cv2.VideoCapture``; the ZED 2 is one in UVC mode), the floor calibrated by
ArUco markers at known poses to a homography, obstacles segmented by colour and tracked into convex
floor polygons with velocity and covariance.

Layers, as for the other drivers: ``calibration`` (the camera and floor model: intrinsics, markers,
homography), ``tracking`` (frame -> blobs -> tracked convex obstacles), ``device`` (frames from a
``cv2.VideoCapture`` source: a camera index or a video file).
"""
