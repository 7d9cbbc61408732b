"""Physics solvers: Taichi kernels over numpy model descriptions (no torch, no genesis_lite)."""
