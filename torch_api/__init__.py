"""Active policy iteration for PyTorch and TorchRL (Akiyama, Hachiya & Sugiyama, 2010)."""
