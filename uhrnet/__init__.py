"""uhrnet: UHRNet (Wang et al. 2023) and baselines for single-shot FPP height estimation."""

__version__ = "0.1.0"
