"""The lab's `hpgs` commands. The plugin finds them through the `hpgs.commands` entry point group (pyproject.toml:
`bench = "hpgs_lab.cli:bench"`), or through $HPGS_COMMANDS in a checkout that is not pip-installed; it never
imports the lab. This module stays light: `hpgs --help` imports it for the summary, and the command's own module
(`hpgs_lab.runs`) only when `hpgs bench` runs.
"""

from __future__ import annotations

from hpgs_ns.cli import Command

bench = Command("hpgs_lab.runs:Bench", "Benchmark selectors (test PSNR/SSIM/LPIPS, wall and selection time, memory) on scenes.")
