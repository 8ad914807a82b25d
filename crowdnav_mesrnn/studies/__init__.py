"""The studies behind the result pages: code that runs the predictor comparison and writes what
``docs/results/`` shows.

- :mod:`~crowdnav_mesrnn.studies.plan`: the comparison plan (candidates x models x splits, then seeds), resumable
  (``crowdnav-mesrnn predictor plan``).
- :mod:`~crowdnav_mesrnn.studies.report`: ``docs/results/predictors.md`` and its JSON (``predictor report``).
- :mod:`~crowdnav_mesrnn.studies.claims`: the test of the paper's further claims (``predictor report --claims``).
- :mod:`~crowdnav_mesrnn.studies.plotting`: figures of single test windows (``predictor plot``).

Studies use the library (data, models, training, evaluation); nothing in the library imports a study.
"""
