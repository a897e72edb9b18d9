"""Benchmark suites: named lists of scenes, each with the dataparser and options it is read with.

A suite is a TOML file (`hpgs bench --suite FILE`, or the name of one shipped in `hpgs_lab/suites/`, e.g.
`--suite real6`), so per-scene settings live in the suite rather than in a shell history:

    [[scene]]
    name = "fox"                      # results go under OUT/fox/
    path = "fox-nerfstudio"           # relative to --data-root; or synthetic:<layout>
    dataparser = "nerfstudio-data"    # default: found from the folder (sparse/0 -> mipnerf360, transforms.json)
    options = { downscale-factor = 2, eval-mode = "interval" }
    smoke = false                     # true: a smoke check, left out of every interval
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

from hpgs_ns.errors import UserError

# hpgs_ns.dataparser (nerfstudio) is imported where used: `hpgs bench --help` imports this module.

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

SUITES = Path(__file__).resolve().parent / "suites"
SYNTHETIC = "synthetic:"


class SuiteError(UserError, ValueError):
    """A suite file cannot be read or names something that is not there."""


@dataclass(frozen=True)
class Scene:
    """One scene of a benchmark: where it is and how it is read."""

    name: str
    """Results go under OUT/<name>/."""
    path: Path
    """The scene folder (a `synthetic:<layout>` path is generated first, see `runs.resolve_scenes`)."""
    dataparser: str = "mipnerf360"
    """The `ns-train hpgs` dataparser subcommand."""
    options: Tuple[Tuple[str, str], ...] = ()
    """Dataparser options, as (flag without dashes, value) pairs."""
    smoke: bool = False
    """A smoke check: run and tabulated, never part of an interval."""

    def option_dict(self) -> dict:
        return dict(self.options)

    def with_options(self, **options: str) -> Scene:
        merged = {**self.option_dict(), **{k: str(v) for k, v in options.items()}}
        return Scene(self.name, self.path, self.dataparser, tuple(sorted(merged.items())), self.smoke)


def scene_from_folder(path: Path) -> Scene:
    """A scene given by its folder (`hpgs bench --scenes`): named after the folder, its parser found from it."""
    from hpgs_ns.dataparser import scene_dataparser

    path = Path(path)
    if str(path).startswith(SYNTHETIC):
        return Scene(str(path).replace(":", "-"), path, "mipnerf360")
    return Scene(path.name, path, scene_dataparser(path))


def suite_file(suite: str) -> Path:
    """A suite file path, or the shipped suite of that name."""
    path = Path(suite)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise SuiteError(f"suite file {path} not found; pass a .toml file or one of: {', '.join(shipped_suites())}")
        return path
    shipped = SUITES / f"{suite}.toml"
    if not shipped.is_file():
        raise SuiteError(f"unknown suite {suite!r}; choose one of {', '.join(shipped_suites())} or pass a .toml file")
    return shipped


def shipped_suites() -> List[str]:
    return sorted(p.stem for p in SUITES.glob("*.toml"))


# The keys of a [[scene]] table and the TOML types each takes.
SCENE_KEYS = {"name": (str,), "path": (str,), "dataparser": (str,), "options": (dict,), "smoke": (bool,)}
TOML_TYPE = {str: "a string", dict: "a table", bool: "true or false"}


def check_suite_shape(path: Path, spec: dict) -> List[dict]:
    """The suite's [[scene]] tables, each checked to hold only known keys of the right TOML type (SuiteError naming
    the first that does not: `scene = 5`, a `[scene]` table, `options = "x"`)."""
    entries = spec.get("scene", [])
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise SuiteError(f"{path}: `scene` must be a list of [[scene]] tables (each with name and path), not "
                         f"{type(entries).__name__ if not isinstance(entries, dict) else 'one [scene] table'}; "
                         "write each scene as [[scene]]")
    for k, entry in enumerate(entries):
        for key, value in entry.items():
            kinds = SCENE_KEYS.get(key)
            if kinds is None:
                raise SuiteError(f"{path}: scene {k + 1} has an unknown key {key!r}; the keys are {', '.join(SCENE_KEYS)}")
            if not isinstance(value, kinds) or (kinds == (str,) and not value.strip()):
                raise SuiteError(f"{path}: scene {k + 1}: {key} must be {TOML_TYPE[kinds[0]]}"
                                 f"{' (not empty)' if kinds == (str,) else ''}, not {value!r}; fix the file")
        for option, value in entry.get("options", {}).items():
            if isinstance(value, (dict, list)):
                raise SuiteError(f"{path}: scene {k + 1}: option {option!r} must be a string, number or true/false, not "
                                 f"{value!r}; fix the file")
    return entries


def load_suite(suite: str, data_root: Optional[Path] = None, only: Sequence[str] = ()) -> List[Scene]:
    """The scenes of a suite (those named in `only`, if any), their paths resolved against `data_root` (checked to
    exist, synthetic ones aside)."""
    from hpgs_ns.dataparser import DATAPARSERS, scene_dataparser

    path = suite_file(suite)
    try:
        spec = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise SuiteError(f"{path}: not UTF-8 text (byte {err.object[err.start]:#04x} at offset {err.start}); "
                         "save it as UTF-8") from None
    except tomllib.TOMLDecodeError as err:
        raise SuiteError(f"{path}: not valid TOML ({err}); fix the file") from None
    root = Path(data_root) if data_root is not None else Path(".")
    entries = check_suite_shape(path, spec)
    unknown = sorted(set(only) - {str(e.get("name")) for e in entries})
    if unknown:
        raise SuiteError(f"{path}: no scene called {unknown[0]!r}; its scenes: {', '.join(str(e.get('name')) for e in entries)}")
    scenes = []
    for k, entry in enumerate(entries):
        if "name" not in entry or "path" not in entry:
            raise SuiteError(f"{path}: scene {k + 1} needs a name and a path")
        if only and entry["name"] not in only:
            continue
        raw = str(entry["path"])
        synthetic = raw.startswith(SYNTHETIC)
        folder = Path(raw) if synthetic else root / raw
        if not synthetic and not folder.is_dir():
            raise SuiteError(f"{path}: scene {entry['name']!r}: {folder} does not exist; pass --data-root DIR (the folder holding {raw})")
        parser = entry.get("dataparser") or ("mipnerf360" if synthetic else scene_dataparser(folder))
        if parser not in DATAPARSERS:
            raise SuiteError(f"{path}: scene {entry['name']!r}: unknown dataparser {parser!r}; choose one of "
                             f"{', '.join(DATAPARSERS)} (or leave dataparser out: it is found from the folder)")
        options = tuple(sorted((str(k2), str(v)) for k2, v in entry.get("options", {}).items()))
        scenes.append(Scene(str(entry["name"]), folder, parser, options, bool(entry.get("smoke", False))))
    if not scenes:
        raise SuiteError(f"{path}: no [[scene]] entries; add a [[scene]] table with a name and a path for each scene "
                         f"(e.g. {SUITES / 'real6.toml'})")
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise SuiteError(f"{path}: two scenes are called {next(n for n in names if names.count(n) > 1)!r}; names must differ")
    return scenes
