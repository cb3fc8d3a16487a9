"""The composition root (:mod:`gcs.core.daemon`) and the contracts of what runs inside it."""
