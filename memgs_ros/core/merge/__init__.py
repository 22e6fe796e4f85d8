"""MemGS voxel-based merging of similar Gaussians (reference section 4) and the eigh-free
2-Wasserstein distance it minimises."""
