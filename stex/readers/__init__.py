"""Input readers: turn recordings on disk into colour/depth frames plus a ``stex.camera.Calibration``."""
