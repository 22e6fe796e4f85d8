"""The Gaussian as data: records (numpy), the tensor tuple the rasterizer takes, the trainable map."""
