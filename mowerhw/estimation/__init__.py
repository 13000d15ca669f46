"""Estimator parts both phases use: the ground-speed track and motion model
(:mod:`.odometry`) and the absolute pose fit to known landmarks (:mod:`.posefit`)."""
