"""Geometry, the ground of hil: SE(3) transforms, kinematic chains, robot files, inverse kinematics."""
