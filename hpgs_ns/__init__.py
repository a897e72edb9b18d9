"""hpgs_ns: next-best-view selection for 3D Gaussian Splatting, as a nerfstudio plugin."""

__version__ = "0.1.0"
