"""The paper's experiments on the synthetic benchmark: plan (profiles, runs), driver, scoring, report."""
