"""Evaluation metrics: instance segmentation and 6D pose."""
