"""Calibration: the identification problem, its solvers, identifiability, the noise floor and the folds."""
