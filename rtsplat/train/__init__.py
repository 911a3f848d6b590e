"""RT-Splatting training: data, losses, density control, optimizer surgery, the loop.

Its settings tree is :mod:`rtsplat.train_config` (plain settings, readable without the trainer)."""
