"""The paper's experiments on the synthetic benchmark: plan (profiles, runs), driver, view_eval (one
forward pass per frame scored several ways), report."""
