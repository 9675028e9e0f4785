"""The DeepMapping2 optimiser (the paper's second stage): pose model, M-Net, losses, training."""
