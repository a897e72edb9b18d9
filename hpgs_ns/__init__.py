"""hpgs_ns: next-best-view selection for 3D Gaussian Splatting, as a nerfstudio plugin.

Layout: the nerfstudio plugin at the top (`method_config` -> `pipeline` -> `rounds` -> `datamanager`, `model`,
`dataparser`, `trainer`); `selectors/` (how views are scored) and `preference/` (the human-preference model);
rendering in `cpu_raster` and `render/`; `scenes/` (synthetic scenes, COLMAP models); `bench/` (the benchmark).
"""

import importlib
import importlib.abc
import importlib.util
import sys

__version__ = "0.2.0"

# Modules that moved in 0.2 (old name -> new name). The old names still import (the same module object), so
# user scripts and pickled or YAML-saved references keep working.
MOVED_MODULES = {
    "hpgs_ns.pair_render": "hpgs_ns.render.pair_render",
    "hpgs_ns.viewmats": "hpgs_ns.render.viewmats",
    "hpgs_ns.synthetic_scene": "hpgs_ns.scenes.synthetic",
    "hpgs_ns.colmap_model": "hpgs_ns.scenes.colmap_model",
    "hpgs_ns.stress": "hpgs_ns.bench.stress",
    "hpgs_ns.executors": "hpgs_ns.bench.executors",
    "hpgs_ns.collect": "hpgs_ns.preference.collect",
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old module name as its new module (no copy: `sys.modules` maps both names to one module)."""

    def find_spec(self, fullname, path=None, target=None):
        return importlib.util.spec_from_loader(fullname, self) if fullname in MOVED_MODULES else None

    def create_module(self, spec):
        return importlib.import_module(MOVED_MODULES[spec.name])

    def exec_module(self, module):
        pass  # already executed under its new name


if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.append(_MovedModules())
