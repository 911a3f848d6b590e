"""RT-Splatting training: config, data, losses, density control, optimizer surgery, the loop."""
