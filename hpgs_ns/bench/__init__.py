"""`hpgs bench`: run time against error for every selector, through the real `ns-train hpgs` pipeline.

`protocols` (how many views, when to add), `names` (the reference rows), `runs` (the command, launching runs,
resuming), `results` (`RunResult`, what one run records), `executors` (local, Ray, Slurm), `stress` (perturbed
copies of scenes), `stats` (paired comparisons), `gain_fit` (the early-stop calibration) and `report` (tables,
plots, the results page).
"""
