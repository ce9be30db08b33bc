"""The robot cell around the pipeline: the bin as a box (bin_box) fitted to a capture (bin_fit),
the camera (zivid_camera) and hand-eye calibration (hand_eye)."""
