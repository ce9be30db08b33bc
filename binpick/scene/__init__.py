"""The scene path, in process: a capture's arrays in, the cleaned cloud, its segments and a pose
per part out, one module per step, so that a stage imports only the step it runs.

Steps: `clean` (range, region, floor and walls, the network's voxel grid and normals),
`segment` (FPCC instance labels), `register` (PPF matching per segment and/or over the whole
scene, score filter, duplicate suppression, verification against what the camera saw), `pick` (a
collision-free grasp per part, ranked); `process` loads a part's models once (`PartModels.load`)
and runs the steps on any number of captures. The DVC stages, the benchmarks and the resident
service all call these functions, so they cannot drift apart. Camera frame, metres; poses are
T_cam_from_model.
"""
