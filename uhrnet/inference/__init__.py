"""Inference and deployment: prediction on images of any size, export, deployable forms."""
