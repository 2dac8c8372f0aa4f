"""Compensation: put the robot where the engineer asked, from a calibrated model and measured corrections."""
