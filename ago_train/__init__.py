"""ago_train: data, pseudo-labels, model, losses, training, evaluation (torch)."""
