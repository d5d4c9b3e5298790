"""Studies over many runs: cohort, ensemble, Sobol, calibration, dose, reproduction."""
