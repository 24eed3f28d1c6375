"""The rig and its geometry: camera + projector, calibration files, per-sample jitter."""
