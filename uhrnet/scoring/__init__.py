"""Scoring: evaluation with the paper's metrics and figures, the calibration-free phase residual, speed."""
