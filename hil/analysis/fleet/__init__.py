"""Across a fleet: which robots moved or grew worse since their last calibration, and which to look at first."""
