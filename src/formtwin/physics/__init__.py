"""Physics-based process models: ``bending`` (the two-stage flap bending model) and
``analytic`` (a closed-form stand-in for tests and development, not the FE model)."""
