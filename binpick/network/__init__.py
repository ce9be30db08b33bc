"""FPCC instance segmentation (Xu et al., Neurocomputing 2022) in PyTorch."""
