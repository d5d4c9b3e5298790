"""Running the model: run specs, the driver, checkpoints, locks, results, farm, fidelity, plots."""
