import os

import torch

os.environ.setdefault("MPLBACKEND", "Agg")
torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)  # small batched ops: one thread is fastest and deterministic
