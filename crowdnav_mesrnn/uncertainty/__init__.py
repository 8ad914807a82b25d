"""Uncertainty regions around forecasts, by conformal prediction.

- :mod:`~crowdnav_mesrnn.uncertainty.conformal`: scores, split-conformal thresholds, calibrations, coverage.
- :mod:`~crowdnav_mesrnn.uncertainty.calibration`: split conformal on validation windows, coverage on the held-out
  scene (``crowdnav-mesrnn predictor calibrate``).
- :mod:`~crowdnav_mesrnn.uncertainty.online_conformal`: thresholds tracked over a scene with delayed feedback.

``calibration`` imports ``online_conformal``; both import ``conformal``, which imports neither.
"""
