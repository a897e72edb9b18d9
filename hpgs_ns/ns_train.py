"""The `ns-train hpgs` command line that `hpgs demo`, `hpgs collect` and `hpgs bench` run (and print).

They train through the real `ns-train` in a subprocess rather than in-process, so each run is exactly what a
user would type (the command is recorded with every benchmark result), and a crash or a leak ends with the run.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Mapping, Optional, Sequence, Union

SELECTION_PREFIX = "pipeline.selection."  # where the selection loop's options are set on the command line
Value = Union[str, int, float, bool, Path, Sequence[Union[str, int, float]]]


def ns_train_command(
    data: Path,
    output_dir: Path,
    experiment: str,
    timestamp: str,
    steps: int,
    datamanager: Optional[Mapping[str, Value]] = None,
    selection: Optional[Mapping[str, Value]] = None,
    model: Optional[Mapping[str, Value]] = None,
    trainer: Optional[Mapping[str, Value]] = None,
    extra: Sequence[str] = (),
    dataparser: Optional[str] = None,
    dataparser_options: Optional[Mapping[str, Value]] = None,
) -> List[str]:
    """`python -m nerfstudio.scripts.train hpgs ...` for one run of `steps` steps in
    `output_dir/experiment/hpgs/timestamp`, with tensorboard instead of the viewer (with the viewer on, ns-train
    never exits), one checkpoint at the end and no evaluation during training.

    `datamanager`, `model` and `trainer` map option names (with dashes or underscores) to values:
    `{"num-initial-views": 6}` -> `--pipeline.datamanager.num-initial-views 6`; `selection` holds the selection
    loop's options (`{"selector": "fisher"}` -> `--pipeline.selection.selector fisher`); a sequence value gives several
    words, a bool `True`/`False`. `extra` is appended as given (then `--vis tensorboard`). The dataparser subcommand (default
    `mipnerf360`) comes last, with its options after it, as tyro reads them: `mipnerf360 --downscale-factor 2`."""
    args = [
        sys.executable, "-m", "nerfstudio.scripts.train", "hpgs",
        "--data", str(data), "--output-dir", str(output_dir), "--experiment-name", experiment,
        "--timestamp", timestamp,
        "--max-num-iterations", str(steps), "--steps-per-save", str(steps),
        "--steps-per-eval-all-images", str(10 * steps), "--steps-per-eval-image", str(10 * steps),
    ]
    for prefix, options in (("", trainer), ("pipeline.datamanager.", datamanager), (SELECTION_PREFIX, selection),
                            ("pipeline.model.", model)):
        for name, value in (options or {}).items():
            args += [f"--{prefix}{name.replace('_', '-')}", *_words(value)]
    # `--vis` after the extra arguments: no extra can turn the viewer back on (ns-train would never exit).
    args += [*extra, "--vis", "tensorboard"]
    if dataparser is not None or dataparser_options:
        args.append(dataparser or "mipnerf360")
        for name, value in (dataparser_options or {}).items():
            args += [f"--{name.replace('_', '-')}", *_words(value)]
    return args


def _words(value: Value) -> List[str]:
    if isinstance(value, (list, tuple)):
        return [str(v) for v in value]
    return [str(value)]

