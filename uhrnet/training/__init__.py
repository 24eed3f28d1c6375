"""Training: data, augmentation, splits, losses, the trainer and its run folder."""
