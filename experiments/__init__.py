"""absl entry points: evaluate, benchmark (and the training experiments)."""
