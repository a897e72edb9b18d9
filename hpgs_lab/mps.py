"""CUDA MPS for runs that share a GPU: start one control daemon per GPU for a sweep, give its runs the two variables,
tell whether a run really was an MPS client, and quit the daemons after.

Without MPS, processes on one GPU take turns on it (time slicing) and their small kernels never overlap; under MPS
their kernels run side by side. MPS is NVIDIA's user-space daemon (`nvidia-cuda-mps-control`): it changes no GPU
setting. Each daemon gets its own pipe and log folders and sees one GPU, named by UUID: a daemon remaps device
indices, so a client asking for index 2 of a daemon that sees one GPU would find none (NVIDIA's MPS guide,
"CUDA_VISIBLE_DEVICES"). A daemon the user already runs (at $CUDA_MPS_PIPE_DIRECTORY or the default folder) is
used as it is and left running.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Literal, Optional, Sequence

from hpgs_ns.errors import UserError

CONTROL = "nvidia-cuda-mps-control"
# Where drivers put the binary when it is not on PATH (/usr/local/nvidia/bin: containers with the driver mounted).
DRIVER_FOLDERS = ("/usr/local/nvidia/bin", "/usr/bin", "/usr/local/cuda/bin", "/usr/lib/nvidia")
DEFAULT_PIPE = "/tmp/nvidia-mps"
PIPE, LOG = "CUDA_MPS_PIPE_DIRECTORY", "CUDA_MPS_LOG_DIRECTORY"
MpsMode = Literal["auto", "on", "off"]
INSTALL = ("install the NVIDIA driver's CUDA MPS tools (`nvidia-cuda-mps-control`) or put its folder on PATH, or pass "
           "--mps off")


def find_control() -> Optional[str]:
    """The MPS control binary on PATH or in the driver's usual folders, or None."""
    found = shutil.which(CONTROL)
    if found:
        return found
    for folder in DRIVER_FOLDERS:
        path = Path(folder) / CONTROL
        if path.is_file() and os.access(path, os.X_OK):
            return str(path)
    return None


@dataclass
class Daemon:
    """One MPS control daemon: its binary, pipe and log folders, the GPU it serves (None: every GPU it sees), and
    whether this process started it (and so quits it)."""

    control: str
    pipe: str
    log: str
    gpu: Optional[str] = None
    owned: bool = True

    def env(self) -> Dict[str, str]:
        """What a client run needs: the two folders, and its GPU by the name the daemon knows it by."""
        env = {PIPE: self.pipe, LOG: self.log}
        if self.gpu is not None:
            env["CUDA_VISIBLE_DEVICES"] = self.gpu
        return env

    def ask(self, command: str, timeout: float = 10.0) -> Optional[str]:
        """The daemon's answer to one control command, or None when it does not answer."""
        try:
            done = subprocess.run([self.control], input=command + "\n", capture_output=True, text=True,
                                  timeout=timeout, env={**os.environ, PIPE: self.pipe, LOG: self.log})
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout if done.returncode == 0 else None

    def servers(self) -> List[int]:
        return [int(w) for w in (self.ask("get_server_list") or "").split() if w.isdigit()]

    def clients(self) -> List[int]:
        """PIDs of the processes its servers serve now."""
        return [int(w) for s in self.servers() for w in (self.ask(f"get_client_list {s}") or "").split() if w.isdigit()]

    def serves(self, pid: int) -> bool:
        return pid in self.clients()

    def running(self) -> bool:
        return (Path(self.pipe) / "control").exists() and self.ask("get_server_list") is not None

    def quit(self, wait: float = 30.0) -> None:
        """Quit a daemon this process started (MPS waits for its clients to end), then remove its folders."""
        if not self.owned:
            return
        self.ask("quit", timeout=wait)
        deadline = time.monotonic() + wait
        while (Path(self.pipe) / "control").exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        for folder in (self.pipe, self.log):
            shutil.rmtree(folder, ignore_errors=True)


def user_daemon(control: str, gpu: Optional[str] = None) -> Optional[Daemon]:
    """A daemon already running where clients look by default ($CUDA_MPS_PIPE_DIRECTORY, else /tmp/nvidia-mps)."""
    pipe = os.environ.get(PIPE) or DEFAULT_PIPE
    daemon = Daemon(control, pipe, os.environ.get(LOG) or "/var/log/nvidia-mps", gpu, owned=False)
    return daemon if daemon.running() else None


def start_daemon(control: str, gpu: Optional[str] = None, timeout: float = 15.0) -> Daemon:
    """A new daemon with its own folders under the temp folder, seeing only `gpu` when given."""
    pipe = tempfile.mkdtemp(prefix="hpgs-mps-pipe-")
    log = tempfile.mkdtemp(prefix="hpgs-mps-log-")
    daemon = Daemon(control, pipe, log, gpu)
    env = {**os.environ, PIPE: pipe, LOG: log}
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    try:
        done = subprocess.run([control, "-d"], env=env, capture_output=True, text=True, timeout=timeout)
        failed = done.returncode != 0 and (done.stderr or done.stdout).strip()
    except (OSError, subprocess.SubprocessError) as exc:
        failed = str(exc)
    deadline = time.monotonic() + timeout
    while not failed and not daemon.running():
        if time.monotonic() > deadline:
            failed = f"no control socket after {timeout:.0f} s"
        time.sleep(0.1)
    if failed:
        log_tail = ""
        with contextlib.suppress(OSError):
            log_tail = (Path(log) / "control.log").read_text().strip().splitlines()[-1]
        for folder in (pipe, log):
            shutil.rmtree(folder, ignore_errors=True)
        why = str(failed).strip().splitlines()[-1] if str(failed).strip() else "exit status"
        raise UserError(f"hpgs bench: the CUDA MPS daemon ({control}) did not start ({why}"
                        f"{'; its log: ' + log_tail if log_tail else ''}); stop another MPS daemon on these GPUs or "
                        "pass --mps off")
    return daemon


def gpu_uuids(ids: Sequence[str]) -> Dict[str, str]:
    """CUDA_VISIBLE_DEVICES ids -> `GPU-<uuid>` (what a daemon and its clients agree on); {} if torch cannot say."""
    try:
        import torch

        return {gid: f"GPU-{torch.cuda.get_device_properties(k).uuid}" for k, gid in enumerate(ids)}
    except Exception:  # an old torch without .uuid, or no driver: the daemons then see every GPU
        return {}


def wanted(mode: MpsMode, sharing: bool) -> bool:
    """Whether a sweep runs under MPS: `on` always (one line if the binary is missing), `auto` when runs share a
    GPU and the binary is there, `off` never."""
    if mode == "off":
        return False
    control = find_control()
    if control is None:
        if mode == "on":
            raise UserError(f"hpgs bench: --mps on but {CONTROL} is not on PATH nor in the driver's folders "
                            f"({', '.join(DRIVER_FOLDERS) or 'none'}); {INSTALL}")
        return False
    return mode == "on" or sharing


@contextlib.contextmanager
def daemons_for(gpus: Sequence[str]) -> Iterator[Dict[Optional[str], Daemon]]:
    """One daemon per GPU id in `gpus` (one for the machine when it has none: `--mps on` on a CPU box), quit on exit
    whatever happens; a user's running daemon serves every GPU instead and is left running."""
    control = find_control()
    if control is None:
        raise UserError(f"hpgs bench: {CONTROL} not found; {INSTALL}")
    existing = user_daemon(control)
    if existing is not None:
        yield {gid: existing for gid in (list(gpus) or [None])}
        return
    uuids = gpu_uuids(gpus) if gpus else {}
    started: Dict[Optional[str], Daemon] = {}
    try:
        for gid in list(gpus) or [None]:
            started[gid] = start_daemon(control, uuids.get(gid) if gid is not None else None)
        yield started
    finally:
        for daemon in started.values():
            daemon.quit()


def observed(pid: int, env: Dict[str, str]) -> Optional[bool]:
    """Whether process `pid`, started with `env`, is a client of an MPS server now; None where no daemon answers."""
    control = find_control()
    if control is None:
        return None
    daemon = Daemon(control, env.get(PIPE) or DEFAULT_PIPE, env.get(LOG) or "", owned=False)
    if not (Path(daemon.pipe) / "control").exists():
        return None
    return daemon.serves(pid)


# Errors a run prints when its MPS server went down under it (another client's fatal fault ends every client on
# that GPU), as torch and the CUDA driver spell them.
MPS_FAULTS = ("mps server", "mps client", "cudaerrormps", "cuda_error_mps", "unspecified launch failure",
              "illegal memory access", "the remote procedural call")


def looks_like_mps_fault(error: str) -> bool:
    text = error.lower()
    return any(marker in text for marker in MPS_FAULTS)
