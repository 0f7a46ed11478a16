"""The robot model, its trajectories and the scene it moves in (read, validated, kinematics)."""
