"""Evaluation: decomposition errors against Cycles ground truth, FID/KID, and the report."""
