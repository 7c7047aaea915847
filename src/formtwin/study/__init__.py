"""The paper's study: pseudo-data, the six simulation series, metrics and the report."""
