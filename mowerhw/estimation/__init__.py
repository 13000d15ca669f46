"""Estimator parts both phases use: the ground-speed track and motion model
(:mod:`.odometry`), the absolute pose fit to known landmarks (:mod:`.posefit`), and lift,
tilt and collision from the specific force and the mower's switches (:mod:`.safety`: the
supervisor and the simulator judge them the same way)."""
