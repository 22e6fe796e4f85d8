"""How the package runs on a machine: CPU tuning and the numba switch, dying with the parent
process, atomic file writes, and the command-worker base every actor derives from."""
