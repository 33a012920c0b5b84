"""A simulation run: the time-stepping loop, its output directory (series,
checkpoints, summary), pictures, and interruption by signals."""
