"""A crash-safe training run: the loop, vector collection, run directory, TensorBoard
log, heartbeat and watchdog, curriculum, learning-rate probe, scenario-file check."""
