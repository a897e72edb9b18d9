"""`hpgs bench`: run time against error for every selector, through the real `ns-train hpgs` pipeline.

`protocols` (how many views, when to add), `runs` (the command, launching runs, resuming), `executors` (local,
Ray, Slurm), `stress` (perturbed copies of scenes) and `report` (tables and plots, stress's too).
"""
