"""Where work items run: here (`local`), on a Ray cluster (`ray`) or on Slurm (`slurm`).

The scheduling is the cluster's: Ray tasks with `num_gpus`/`num_cpus`, or submitit job arrays. An executor maps a
worker function `fn(item, env) -> value` over items and yields each result (`Done`) as it arrives; what a worker
does is its caller's business (`hpgs bench`: `bench.runs.sweep_worker`). Ray and submitit are optional
(`pip install 'hpgs-ns[cluster]'`) and imported only when chosen.
"""

from __future__ import annotations

import contextlib
import os
import queue
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Sequence

from rich.console import Console

from hpgs_lab import mps as cuda_mps
from hpgs_lab.mps import MpsMode
from hpgs_ns.errors import UserError

CONSOLE = Console(stderr=True)
INSTALL = "pip install 'hpgs-ns[cluster]'"

# A worker function: (item, extra environment for the run's subprocess) -> picklable value.
Worker = Callable[[Any, Dict[str, str]], Any]


@dataclass
class ExecutorConfig:
    """Where the runs execute. `local` runs them here, one after another (or `runs_per_gpu` on every visible
    GPU); `ray` submits each run as a Ray task; `slurm` submits a job array through submitit."""

    executor: Literal["local", "ray", "slurm"] = "local"
    """Run locally, as Ray tasks, or as Slurm jobs (the last two need `pip install 'hpgs-ns[cluster]'`)."""
    runs_per_gpu: Optional[int] = None
    """Runs sharing one GPU at a time (one run of a small scene leaves an H100 mostly idle): `local` runs this many
    on every visible GPU (CPU-only: one run at a time), Ray reserves 1/N GPU per run, Slurm runs N per job. Default
    12 under CUDA MPS, else 4: on the FisherRF protocol MPS gave 112 runs per GPU-hour at 12 (155 at 24), and without
    MPS 4 gives most of 8's throughput at half its latency (docs/benchmark.md, "Full GPUs and throughput"). Wall
    and per-step times of concurrent runs are not those of a run alone: the report keeps timing columns from solo
    runs (`--runs-per-gpu 1`)."""
    mps: MpsMode = "auto"
    """CUDA MPS for runs sharing a GPU, so their kernels overlap instead of taking turns: `auto` when more than one
    run shares a GPU and `nvidia-cuda-mps-control` is on PATH or in the driver's folders, `on`, or `off`. `local`
    and each Slurm job start one daemon per GPU and quit them when the runs end (a daemon you already run is used
    and left running); on Ray, start it on the workers yourself (docs/benchmark.md)."""
    local_workers: Optional[int] = None
    """Concurrent runs for `local`: default `runs_per_gpu` per visible CUDA GPU (each sees only its own), else 1."""
    ray_address: Optional[str] = None
    """Ray cluster to join (`auto`, `HOST:6379`); default $RAY_ADDRESS, else a new local one."""
    ray_gpus_per_run: Optional[float] = None
    """GPUs each Ray task reserves (default 1 / runs-per-gpu; 0 for CPU runs)."""
    ray_cpus_per_run: float = 1.0
    """CPUs each Ray task reserves; also the run's OMP_NUM_THREADS (at least 1)."""
    slurm_partition: Optional[str] = None
    """Slurm partition (default: the cluster's)."""
    slurm_time_min: int = 60
    """Time limit of each Slurm job, minutes."""
    slurm_gpus_per_run: int = 1
    """GPUs per Slurm job (it runs `runs_per_gpu` runs at once on them)."""
    slurm_cpus_per_run: int = 8
    """CPUs per Slurm job; also the run's OMP_NUM_THREADS."""
    slurm_mem_gb: Optional[int] = None
    """Memory per Slurm job (default: the partition's)."""
    slurm_parallelism: int = 64
    """At most this many jobs of the array run at once."""
    slurm_cluster: Literal["slurm", "local", "debug"] = "slurm"
    """submitit backend: `slurm`, or `local`/`debug` to try the Slurm path on one machine (tests)."""


@dataclass
class Done:
    """One finished item: its index in the submitted list and the worker's value, or why there is none."""

    index: int
    value: Any = None
    error: Optional[str] = None


def thread_env(threads: int) -> Dict[str, str]:
    # Fixed intra-op threads: CPU results then depend only on the seed, not on the worker's core count.
    return {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}


def visible_gpus() -> List[str]:
    """CUDA device ids this process may use, as CUDA_VISIBLE_DEVICES spells them."""
    import torch

    n = torch.cuda.device_count()
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [d.strip() for d in listed.split(",") if d.strip()] if listed else [str(i) for i in range(n)]
    return ids[:n]


class LocalExecutor:
    """Runs here: in-process one after another, or `workers` at a time, each pinned to one GPU if there are any."""

    def __init__(self, config: ExecutorConfig):
        self.config = config

    def map(self, fn: Worker, items: Sequence[Any]) -> Iterator[Done]:
        gpus = visible_gpus()
        workers = self.config.local_workers or (len(gpus) * runs_per_gpu(self.config) if gpus else 1)
        under_mps = cuda_mps.wanted(self.config.mps, sharing=bool(gpus) and workers > len(gpus))
        with contextlib.ExitStack() as stack:
            daemons = stack.enter_context(cuda_mps.daemons_for(gpus)) if under_mps else {}
            if under_mps:
                CONSOLE.print(f"hpgs bench: CUDA MPS on ({len(set(map(id, daemons.values())))} daemon(s))")
            if workers == 1:
                only = gpus[0] if daemons and gpus else None  # under --mps on, the first GPU's daemon
                for i, item in enumerate(items):
                    yield Done(i, fn(item, slot_env(only, daemons)))
                return
            # Each slot is one GPU (runs_per_gpu slots per GPU; none on CPU); a run takes a slot for its whole duration.
            slots: queue.Queue[Optional[str]] = queue.Queue()
            for k in range(workers):
                slots.put(gpus[k % len(gpus)] if gpus else None)
            threads = os.environ.get("OMP_NUM_THREADS") or str(max((os.cpu_count() or 1) // workers, 1))

            def call(item: Any) -> Any:
                slot = slots.get()
                env = {**thread_env(int(threads)), **slot_env(slot, daemons)}
                try:
                    return fn(item, env)
                finally:
                    slots.put(slot)

            with ThreadPoolExecutor(workers) as pool:
                futures = {pool.submit(call, item): i for i, item in enumerate(items)}
                for future in as_completed(futures):
                    yield Done(futures[future], future.result())


def slot_env(gpu: Optional[str], daemons: Dict[Optional[str], cuda_mps.Daemon]) -> Dict[str, str]:
    """A run's GPU and, under MPS, its daemon's folders (and the GPU by the name that daemon knows it by)."""
    env = {"CUDA_VISIBLE_DEVICES": gpu} if gpu is not None else {}
    daemon = daemons.get(gpu) or daemons.get(None)
    if daemon is not None:
        env.update(daemon.env())
    return env


class RayExecutor:
    """One Ray task per item, reserving `ray_gpus_per_run` GPUs and `ray_cpus_per_run` CPUs."""

    def __init__(self, config: ExecutorConfig):
        try:
            import ray
        except ImportError:
            raise UserError(f"hpgs bench: --executor ray needs Ray: {INSTALL}") from None
        self.ray, self.config = ray, config

    def map(self, fn: Worker, items: Sequence[Any]) -> Iterator[Done]:
        ray, cfg = self.ray, self.config
        started_here = False
        if not ray.is_initialized():
            address = cfg.ray_address or os.environ.get("RAY_ADDRESS")
            started_here = address is None
            if started_here:
                start_local_ray(ray)
            else:
                ray.init(address=address, log_to_driver=False)
        gpus = ray.cluster_resources().get("GPU", 0)
        per_run = ray_gpus_per_run(cfg)
        if per_run > gpus:
            message = f"--ray-gpus-per-run {per_run:g} but the Ray cluster has {gpus:g} GPUs"
            if started_here:
                raise UserError(f"hpgs bench: {message}; pass --ray-gpus-per-run 0 for CPU runs")
            CONSOLE.print(f"[yellow]{message}: tasks wait until the autoscaler adds GPU nodes")
        task = ray.remote(num_gpus=per_run, num_cpus=cfg.ray_cpus_per_run)(fn)
        env = thread_env(max(int(cfg.ray_cpus_per_run), 1))
        refs = {task.remote(item, env): i for i, item in enumerate(items)}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for ref in ready:
                try:
                    yield Done(refs[ref], ray.get(ref))
                except Exception as exc:  # the worker died (node lost, out of memory): report, keep the rest
                    yield Done(refs[ref], error=f"Ray task failed: {exc}")


def runs_per_device(config: ExecutorConfig) -> int:
    """How many runs share one device at a time under `config` (1: a run has its GPU, or the CPU, to itself)."""
    if config.executor == "ray":
        share = ray_gpus_per_run(config)
        return max(int(round(1 / share)), 1) if share > 0 else 1
    if config.executor == "slurm":
        return runs_per_gpu(config)
    gpus = visible_gpus()
    if config.local_workers is not None:
        return max(1, config.local_workers // max(len(gpus), 1))
    return runs_per_gpu(config) if gpus else 1


MPS_RUNS_PER_GPU, PLAIN_RUNS_PER_GPU = 12, 4


def runs_per_gpu(config: ExecutorConfig) -> int:
    """`--runs-per-gpu`, or its default: 12 where the runs will share GPUs under MPS (local: `--mps` and the binary
    here; Ray and Slurm: `--mps on`), else 4."""
    if config.runs_per_gpu is not None:
        return max(config.runs_per_gpu, 1)
    if config.executor == "local":
        under_mps = cuda_mps.wanted(config.mps, sharing=True)
    else:
        under_mps = config.mps == "on"
    return MPS_RUNS_PER_GPU if under_mps else PLAIN_RUNS_PER_GPU


def ray_gpus_per_run(config: ExecutorConfig) -> float:
    """What each Ray task reserves: `--ray-gpus-per-run`, else 1 / `--runs-per-gpu`."""
    if config.ray_gpus_per_run is not None:
        return float(config.ray_gpus_per_run)
    return 1.0 / runs_per_gpu(config)


def start_local_ray(ray, attempts: int = 3, num_cpus: Optional[int] = None) -> None:
    """A local Ray cluster on this machine (all its CPUs and GPUs), retried if its startup times out.

    The raylet gives its agents a fixed 15 s to start (ray-project/ray#65983); on a small, busy host their Python
    imports can take longer, and a second try usually fits."""
    for attempt in range(1, attempts + 1):
        try:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
            return
        except Exception as exc:
            ray.shutdown()
            if attempt == attempts:
                first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                raise UserError(f"hpgs bench: could not start a local Ray cluster ({attempts} tries: {first}); pass "
                                "--ray-address of a running cluster or use --executor local") from exc
            CONSOLE.print(f"[yellow]local Ray cluster did not start (try {attempt} of {attempts}); retrying")


class SlurmExecutor:
    """A submitit job array: one Slurm job per `runs_per_gpu` items (or submitit's local/debug executor for tests)."""

    def __init__(self, config: ExecutorConfig, folder: Path):
        try:
            import submitit
        except ImportError:
            raise UserError(f"hpgs bench: --executor slurm needs submitit: {INSTALL}") from None
        self.submitit, self.config, self.folder = submitit, config, folder

    def map(self, fn: Worker, items: Sequence[Any]) -> Iterator[Done]:
        cfg = self.config
        executor = self.submitit.AutoExecutor(folder=self.folder / "%j", cluster=cfg.slurm_cluster)
        params: Dict[str, Any] = {
            "name": "hpgs-bench", "timeout_min": cfg.slurm_time_min, "nodes": 1, "tasks_per_node": 1,
            "gpus_per_node": cfg.slurm_gpus_per_run, "cpus_per_task": cfg.slurm_cpus_per_run,
            "slurm_array_parallelism": cfg.slurm_parallelism,
        }
        if cfg.slurm_partition:
            params["slurm_partition"] = cfg.slurm_partition
        if cfg.slurm_mem_gb:
            params["mem_gb"] = cfg.slurm_mem_gb
        executor.update_parameters(**params)
        # runs_per_gpu runs share each job (and its GPUs and CPUs), run side by side by `run_together`.
        n = runs_per_gpu(cfg)
        env = thread_env(max(cfg.slurm_cpus_per_run // n, 1))
        chunks = [list(range(start, min(start + n, len(items)))) for start in range(0, len(items), n)]
        jobs = executor.map_array(run_together, [fn] * len(chunks), [[items[i] for i in c] for c in chunks],
                                  [env] * len(chunks), [cfg.mps] * len(chunks))
        index = {id(job): chunk for job, chunk in zip(jobs, chunks)}
        CONSOLE.print(f"submitted {len(jobs)} jobs ({cfg.slurm_cluster}), logs under {self.folder}")
        poll = 10.0 if cfg.slurm_cluster == "slurm" else 0.5
        for job in self.submitit.helpers.as_completed(jobs, poll_frequency=poll):
            try:
                values = job.result()
            except Exception as exc:  # cancelled, timed out, or the node failed
                error = f"job {job.job_id} failed: {str(exc).strip().splitlines()[-1]}"
                for i in index[id(job)]:
                    yield Done(i, error=error)
                continue
            for i, value in zip(index[id(job)], values):
                yield Done(i, value)


def run_together(fn: Worker, items: Sequence[Any], env: Dict[str, str], mps_mode: MpsMode = "off") -> List[Any]:
    """`fn` on every item at once, in threads (the runs of one Slurm job sharing its GPU), under MPS when `mps_mode`
    asks for it and more than one run shares a GPU."""
    gpus = visible_gpus()
    under_mps = cuda_mps.wanted(mps_mode, sharing=len(items) > max(len(gpus), 1))
    with cuda_mps.daemons_for(gpus) if under_mps else contextlib.nullcontext({}) as daemons:
        slot = [gpus[k % len(gpus)] if gpus else None for k in range(len(items))]
        envs = [{**env, **slot_env(slot[k], daemons)} if daemons else env for k in range(len(items))]
        if len(items) == 1:
            return [fn(items[0], envs[0])]
        with ThreadPoolExecutor(len(items)) as pool:
            return list(pool.map(lambda k: fn(items[k], envs[k]), range(len(items))))


def make_executor(config: ExecutorConfig, out: Path):
    if config.executor == "ray":
        return RayExecutor(config)
    if config.executor == "slurm":
        return SlurmExecutor(config, out / "_submitit")
    return LocalExecutor(config)
