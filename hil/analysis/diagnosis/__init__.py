"""Diagnosis: the baseline, the screening and forward selection of effects, rivals and evidence, the open
questions and the pipeline that runs them."""
