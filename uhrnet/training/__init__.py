"""Training: losses, the trainer, weight averaging, distributed runs, its TensorBoard log, and label-free
adaptation (``adapt``: a training loop on unlabelled real images through the rig)."""
