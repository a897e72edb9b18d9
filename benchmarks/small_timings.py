"""Speed figures the tests used to assert (issue #65: a timed assert fails on a slow or busy machine without
finding a bug; the tests keep socket timeouts as hang guards, and the figures are measured here):

- `bootstrap_10000_s`: `hpgs_lab.stats.hierarchical_bootstrap` with 10000 resamples over 6 scenes x 3 seeds (the
  test asserted < 0.5 s);
- `label_burst_50_s`: `hpgs label`'s server answering 50 label posts that all connected before it accepted any
  (the listen backlog holds them; the test asserted < 5 s: none waited for a SYN retransmission);
- `label_refuse_oversized_s`: its 413 to a request announcing a 200 MB body and sending none (the test asserted
  < half the server's socket timeout: the body is not waited for).

Each figure is the median of `--runs` runs after one untimed run. Prints a table; writes the JSON (figures, runs,
core count, load average) to --out.

    PYTHONPATH=. python benchmarks/small_timings.py [--out benchmarks/results/small_timings.json] [--runs 5]
"""

from __future__ import annotations

import argparse
import csv
import http.client
import json
import os
import platform
import socket
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Dict, List

from PIL import Image


def bootstrap_seconds() -> float:
    import numpy as np

    from hpgs_lab.stats import hierarchical_bootstrap

    rng = np.random.default_rng(0)
    gains = {f"scene{s}": {k: float(rng.normal()) for k in range(3)} for s in range(6)}
    start = time.perf_counter()
    hierarchical_bootstrap(gains, n_boot=10000)
    return time.perf_counter() - start


def _server(folder: Path, pairs: int):
    from hpgs_ns.preference import label_server as ls

    Image.new("RGB", (8, 8)).save(folder / "a.png")
    with open(folder / "pairs.csv", "w", newline="") as f:
        csv.writer(f).writerows([["Image_1", "Image_2", "Human Preference"]] + [["a.png", "a.png", ""]] * pairs)
    return ls.LabelServer(("127.0.0.1", 0), ls.make_handler(ls.LabelBook(folder / "pairs.csv")))


def label_burst_seconds() -> float:
    """50 clients connect and post before the server accepts; seconds from its first accept to the last answer."""
    with tempfile.TemporaryDirectory() as tmp:
        server = _server(Path(tmp), 50)
        port, sent, codes = server.server_address[1], threading.Barrier(51), [None] * 50

        def client(i: int) -> None:
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            try:
                conn.request("POST", "/api/label", json.dumps({"id": i, "value": "1"}), {"Content-Type": "application/json"})
                sent.wait()
                codes[i] = conn.getresponse().status
            finally:
                conn.close()

        threads = [threading.Thread(target=client, args=(i,)) for i in range(50)]
        try:
            for t in threads:
                t.start()
            sent.wait(timeout=30)
            start = time.monotonic()
            threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
            for t in threads:
                t.join(60)
            elapsed = time.monotonic() - start
        finally:
            server.shutdown()
            server.server_close()
    if codes != [200] * 50:
        raise RuntimeError(f"the burst was not all answered: {codes}")
    return elapsed


def label_refuse_oversized_seconds() -> float:
    """Seconds from sending headers that announce a 200 MB body (and no body) to the server's 413."""
    with tempfile.TemporaryDirectory() as tmp:
        server = _server(Path(tmp), 1)
        port = server.server_address[1]
        threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
        request = (f"POST /api/label HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
                   "Content-Length: 200000000\r\n\r\n").encode()
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
                start = time.monotonic()
                s.sendall(request)
                reply = s.recv(65536)
                elapsed = time.monotonic() - start
        finally:
            server.shutdown()
            server.server_close()
    if not reply.startswith(b"HTTP/1.0 413") and not reply.startswith(b"HTTP/1.1 413"):
        raise RuntimeError(f"expected a 413, got {reply[:40]!r}")
    return elapsed


FIGURES: Dict[str, Callable[[], float]] = {
    "bootstrap_10000_s": bootstrap_seconds,
    "label_burst_50_s": label_burst_seconds,
    "label_refuse_oversized_s": label_refuse_oversized_seconds,
}
ASSERTED = {"bootstrap_10000_s": 0.5, "label_burst_50_s": 5.0, "label_refuse_oversized_s": 5.0}  # the old bounds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/small_timings.json"))
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    runs: Dict[str, List[float]] = {}
    for name, measure in FIGURES.items():
        measure()  # untimed: imports, first-use costs
        runs[name] = [measure() for _ in range(args.runs)]
    figures = {name: statistics.median(values) for name, values in runs.items()}
    print(f"{'figure':<28}{'median s':>10}{'max s':>10}{'old bound s':>13}")
    for name, value in figures.items():
        print(f"{name:<28}{value:>10.3f}{max(runs[name]):>10.3f}{ASSERTED[name]:>13.1f}")
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    result = {"figures": figures, "runs": runs, "old_bounds": ASSERTED, "cores": os.cpu_count(), "load_average": load,
              "python": platform.python_version(), "machine": platform.machine()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
