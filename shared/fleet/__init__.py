"""The fleet pose graph: every robot's keyframes in one robust graph (odometry, loop
closures within and between robots, the pairwise fits), optimised with GTSAM so that each
robot's own drift is corrected where the closures show it.

`drift` (a VIO-like drift model for benchmarks and tests), `closures` (loop closures with
their relative poses from 3D-3D matches), `graph` (the GTSAM graph and its robust
optimisation), `correct` (the corrected trajectories, clouds and per-robot figures).
"""
