"""hpgs_ns: next-best-view selection for 3D Gaussian Splatting, as a nerfstudio plugin.

Layout: the nerfstudio plugin at the top (`method_config` -> `trainer` -> `pipeline` -> `selection` (the loop),
`datamanager`, `model`, `dataparser`); `selectors/` (how views are scored) and `preference/` (the human-preference
model); rendering in `cpu_raster` and `render/`; `scenes/` (synthetic scenes, COLMAP models). Benchmarking
(`hpgs bench`) is a separate package that imports this one; this one never imports it. Importing the package does
nothing else.
"""

__version__ = "0.5.0"
