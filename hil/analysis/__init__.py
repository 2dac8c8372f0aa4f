"""Analysis of measured data, by job: calibration (the fit), diagnosis (what the model lacks), design (the poses
that decide what is open) and standards (ISO 9283, joint axes, flange geometry); each imports only downward."""
