"""What a trained model says about demonstrations: decoded stacks, which demonstrations to annotate."""
