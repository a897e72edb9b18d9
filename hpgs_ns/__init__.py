"""hpgs_ns: next-best-view selection for 3D Gaussian Splatting, as a nerfstudio plugin.

Layout: the nerfstudio plugin at the top (`method_config` -> `trainer` -> `pipeline` -> `selection` (the loop),
`datamanager`, `model`, `dataparser`); `selectors/` (how views are scored) and `preference/` (the human-preference
model); rendering in `cpu_raster` and `render/`; `scenes/` (synthetic scenes, COLMAP models). The benchmark lab
(`hpgs bench`, statistics, reports) is the separate package `hpgs_lab`, which imports this one and never the other
way (tests/plugin/test_architecture.py). Importing the package does nothing else.
"""

__version__ = "0.4.0"
