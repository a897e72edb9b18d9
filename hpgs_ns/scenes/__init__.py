"""Scene folders: the embedded procedural scenes, and reading and writing COLMAP models."""
