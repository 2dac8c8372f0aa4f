"""Analysis of measured data: calibration, diagnosis of missing effects, residual maps, noise, reports."""
