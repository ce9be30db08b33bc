"""The robot arm: its model from a shipped URDF (arm), configurations among IK solutions
(configuration), timed joint motions (trajectory) and the arm against what the camera measured
(clearance)."""
