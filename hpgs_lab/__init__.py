"""The benchmark lab: `hpgs bench`, run time against error for every selector through the real `ns-train hpgs`
pipeline, and the statistics and reports on its results.

It imports the plugin (hpgs_ns) and never the other way: `hpgs bench` reaches the plugin's `hpgs` command through
the `hpgs.commands` entry point that `cli` declares (pyproject.toml). The experiment scripts that use it are in
benchmarks/ (benchmarks/README.md).

`cli` (the command as the plugin's `hpgs` finds it), `protocols` (how many views, when to add), `names` (the
reference rows), `suites` (scene suites; the shipped ones in suites/*.toml), `runs` (the command, launching runs,
resuming), `results` (`RunResult`, what one run records), `provenance` (what made a run's numbers), `executors`
(local, Ray, Slurm) with `mps` (CUDA MPS for runs sharing a GPU), `stress` (perturbed copies of scenes), `stats`
(paired comparisons), `power` (how many seeds a comparison needs), `gain_fit` (the early-stop calibration) and
`report` (tables, plots, the results page, the paper's table).
"""
