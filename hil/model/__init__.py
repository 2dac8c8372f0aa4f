"""The fitted robot model: effects, the calibrated model that carries them and the residual maps. Compensation
reads it; the analysis that fits it sits above."""
