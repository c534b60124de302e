import os

import torch

os.environ.setdefault("MPLBACKEND", "Agg")
torch.set_default_dtype(torch.float64)
torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
