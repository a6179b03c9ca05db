"""Training: settings, a run in its workdir, level-wise and joint Expectation-Gradient, checkpoints."""
