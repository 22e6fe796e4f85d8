"""Differentiable Gaussian rasterization (project -> bin into tiles -> composite)."""
