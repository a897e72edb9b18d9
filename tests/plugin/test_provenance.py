"""The plugin's own list of the modules that can change a run's numbers (`hpgs_ns.provenance`)."""

from __future__ import annotations

from conftest import REPO

from hpgs_ns import provenance


def test_the_training_path_is_code_and_the_tools_are_not():
    files = provenance.code_files()
    assert files == tuple(sorted(files)) and all(not rel.startswith("/") and rel.endswith(".py") for rel in files)
    for rel in ("model.py", "trainer.py", "pipeline.py", "cpu_raster.py", "selection/rounds.py", "selection/early_stop.py",
                "render/pair_render.py", "scenes/triangulate.py", "strategies/base.py", "strategies/registry.py",
                "selectors/base.py", "selectors/registry.py"):
        assert rel in files, rel
    for rel in ("__init__.py", "cli.py", "viewer.py", "provenance.py", "selectors/fisher.py", "selectors/__init__.py",
                "render/coverage.py", "preference/model.py", "selection/candidate_log.py", "suggest/command.py"):
        assert (provenance.PACKAGE / rel).is_file() and rel not in files, rel


def test_every_module_not_declared_otherwise_counts(tmp_path):
    package = REPO / "hpgs_ns"
    files = set(provenance.code_files(package))
    for path in package.rglob("*.py"):
        rel = path.relative_to(package).as_posix()
        assert (rel in files) == provenance.is_code(rel), rel
    (tmp_path / "strategies").mkdir()
    for rel in ("strategies/new.py", "cli.py", "selectors/new.py", "selectors/base.py"):
        (tmp_path / rel).parent.mkdir(exist_ok=True)
        (tmp_path / rel).write_text("X = 1\n")
    assert provenance.code_files(tmp_path) == ("selectors/base.py", "strategies/new.py")
