"""Measuring results: image metrics (PSNR, SSIM with its compiled kernels), trajectory alignment
and ATE, and scoring a map against ground-truth images."""
