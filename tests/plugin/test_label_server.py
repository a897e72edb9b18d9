"""`hpgs label`: answers saved before they are confirmed, survival of kill -9, resume, oracle, page in Chromium."""

from __future__ import annotations

import csv
import http.client
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import urllib.error
import urllib.request
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import pytest
import tyro
from conftest import CHROMIUM, playwright_or_skip
from PIL import Image

from hpgs_ns.errors import UserError
from hpgs_ns.preference import label_server as ls
from hpgs_ns.preference.pairs import read_pairs

REPO = Path(__file__).resolve().parents[2]
N_IMAGES = 6


@pytest.fixture
def label_dir(tmp_path: Path) -> Path:
    """6 renders (image k is blurrier/darker as k grows), 8 unlabelled pairs, renders.csv with their errors."""
    rng = np.random.default_rng(0)
    for k in range(N_IMAGES):
        img = (rng.random((48, 64, 3)) * (255 - 30 * k)).astype(np.uint8)
        Image.fromarray(img).save(tmp_path / f"r{k}.png")
    pairs = [(0, 1), (2, 0), (3, 4), (5, 1), (2, 3), (4, 0), (1, 3), (5, 2)]
    with open(tmp_path / "pairs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Image_1", "Image_2", "Human Preference"])
        w.writerows([f"r{a}.png", f"r{b}.png", ""] for a, b in pairs)
    with open(tmp_path / "renders.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "step", "view", "psnr", "ssim", "lpips"])
        # image k: psnr falls with k (worse), ssim rises with k (better), lpips rises with k (worse)
        w.writerows([f"r{k}.png", 0, k, 30 - k, 0.5 + 0.05 * k, 0.1 + 0.05 * k] for k in range(N_IMAGES))
    return tmp_path


def _labels(path: Path) -> list:
    return [(p.label, p.skipped) for p in read_pairs(path)]


def test_answers_are_on_disk_when_confirmed_and_undo_clears_them(label_dir):
    book = ls.LabelBook(label_dir / "pairs.csv")
    assert book.state()["pair"]["id"] == 0 and book.state()["remaining"] == 8
    book.answer(0, "1")
    book.answer(1, "0")
    book.answer(2, "skip")
    assert _labels(label_dir / "pairs.csv")[:4] == [(1, False), (0, False), (None, True), (None, False)]
    state = book.state()
    assert (state["labelled"], state["skipped"], state["remaining"], state["pair"]["id"]) == (2, 1, 5, 3)
    assert book.undo() == 2 and book.undo() == 1
    assert _labels(label_dir / "pairs.csv")[:3] == [(1, False), (None, False), (None, False)]
    assert book.state()["pair"]["id"] == 1  # the undone pair comes back first
    # a fresh book (a restarted server) resumes at the first open pair; extra columns survive
    with open(label_dir / "pairs.csv", newline="") as f:
        assert next(csv.reader(f)) == ["Image_1", "Image_2", "Human Preference", "Skipped"]
    assert ls.LabelBook(label_dir / "pairs.csv").state()["pair"]["id"] == 1
    with pytest.raises(ValueError):
        book.answer(3, "maybe")


def _start_server(label_dir: Path) -> tuple:
    proc = subprocess.Popen(_cli(label_dir, "--port", "0"), cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    match = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
    assert match, f"no URL in {line!r}; stderr: {proc.stderr.read() if proc.poll() is not None else ''}"
    return proc, match.group(0)


def _cli(label_dir: Path, *args: str) -> list:
    return [sys.executable, "-m", "hpgs_ns.cli", "label", str(label_dir), "--no-open-browser", *args]


def _post(url: str, body: dict, headers: Optional[dict] = None) -> dict:
    req = urllib.request.Request(url, json.dumps(body).encode(), {"Content-Type": "application/json", **(headers or {})})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


def test_cross_site_posts_and_foreign_hosts_are_refused(label_dir):
    proc, url = _start_server(label_dir)
    before = (label_dir / "pairs.csv").read_bytes()
    try:
        for headers in ({"Origin": "http://evil.example"}, {"Origin": "null"}, {"Host": "evil.example"}):
            with pytest.raises(urllib.error.HTTPError) as err:
                _post(url + "api/label", {"id": 0, "value": "1"}, headers)
            assert err.value.code == 403, headers
        with pytest.raises(urllib.error.HTTPError) as err:  # DNS rebinding: reading through another name
            urllib.request.urlopen(urllib.request.Request(url + "api/state", headers={"Host": "evil.example:80"}), timeout=10)
        assert err.value.code == 403
        assert (label_dir / "pairs.csv").read_bytes() == before
        # the page itself (same origin) still labels
        assert _post(url + "api/label", {"id": 0, "value": "1"}, {"Origin": url.rstrip("/")})["labelled"] == 1
    finally:
        proc.kill()
        proc.wait(10)
        proc.stdout.close()
        proc.stderr.close()
    assert _labels(label_dir / "pairs.csv")[0] == (1, False)


def test_server_survives_kill_9_with_every_confirmed_label(label_dir):
    proc, url = _start_server(label_dir)
    try:
        answers = {0: "1", 1: "0", 2: "skip", 3: "1"}
        for i, value in answers.items():
            state = _post(url + "api/label", {"id": i, "value": value})
            assert state["pair"]["id"] == i + 1
        with urllib.request.urlopen(url + "img/0/2", timeout=10) as r:
            assert r.headers["Content-Type"] == "image/png" and r.read() == (label_dir / "r1.png").read_bytes()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        proc.stdout.close()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert _labels(label_dir / "pairs.csv")[:5] == [(1, False), (0, False), (None, True), (1, False), (None, False)]
    assert not list(label_dir.glob(".pairs.csv.*"))  # no temporary files left behind
    # a kill -9 in the middle of a save leaves the temporary file (the CSV stays whole): the restart removes it
    fd, tmp = tempfile.mkstemp(prefix=".pairs.csv.", suffix=".tmp", dir=label_dir)
    os.write(fd, b"Image_1,Image_2,Human Pref")
    os.close(fd)
    proc, url = _start_server(label_dir)  # resumes where it stopped
    try:
        assert not Path(tmp).exists()
        with urllib.request.urlopen(url + "api/state", timeout=10) as r:
            state = json.loads(r.read())
        assert (state["pair"]["id"], state["labelled"], state["skipped"], state["remaining"]) == (4, 3, 1, 4)
    finally:
        proc.kill()
        proc.wait(10)
        proc.stdout.close()
        proc.stderr.close()


@pytest.mark.parametrize("metric", ["psnr", "ssim", "lpips"])
def test_oracle_labels_the_worse_image_by_metric(label_dir, metric):
    ls.Label(label_dir, oracle=metric).main()
    pairs = read_pairs(label_dir / "pairs.csv")
    for p in pairs:
        a, b = int(p.image_1.stem[1:]), int(p.image_2.stem[1:])
        # psnr and lpips say higher k is worse; ssim says lower k is worse
        expected = int(a > b) if metric in ("psnr", "lpips") else int(a < b)
        assert p.label == expected, (metric, p)


def test_oracle_noise_flips_seeded_fraction(label_dir):
    clean_dir = label_dir
    ls.Label(clean_dir, oracle="psnr", noise=1.0).main()
    flipped = [p.label for p in read_pairs(clean_dir / "pairs.csv")]
    expected = [int(int(p.image_1.stem[1:]) > int(p.image_2.stem[1:])) for p in read_pairs(clean_dir / "pairs.csv")]
    assert flipped == [1 - e for e in expected]
    # already-answered pairs are left alone: a second run changes nothing
    ls.Label(clean_dir, oracle="psnr", noise=0.0).main()
    assert [p.label for p in read_pairs(clean_dir / "pairs.csv")] == flipped


def test_oracle_noise_flips_some_answers_the_same_for_a_seed_and_others_for_another(tmp_path, label_dir):
    made = []

    def labels(noise: float, seed: int) -> list:
        copy = tmp_path / "copies" / str(len(made))  # a fresh copy of the unlabelled pairs each time
        made.append(copy)
        shutil.copytree(label_dir, copy, ignore=shutil.ignore_patterns("copies"))
        ls.Label(copy, oracle="lpips", noise=noise, seed=seed).main()
        return [p.label for p in read_pairs(copy / "pairs.csv")]

    clean, first, again, other = labels(0.0, 3), labels(0.5, 3), labels(0.5, 3), labels(0.5, 4)
    flipped = [a != b for a, b in zip(first, clean)]
    assert 0 < sum(flipped) < len(flipped), flipped  # noise 0.5 flips some answers, not none or all
    assert again == first  # the same seed flips the same ones
    assert [a != b for a, b in zip(other, clean)] != flipped  # another seed flips others


def test_malformed_inputs_give_one_line_errors(label_dir):
    (label_dir / "pairs.csv").write_text("Image_1,Image_2,Human Preference\nr0.png,r1.png,7\n")
    with pytest.raises(UserError, match=r"^hpgs label: .*pairs\.csv:2") as info:
        ls.Label(label_dir, open_browser=False).main()
    assert "\n" not in str(info.value) and "Human Preference" in str(info.value)
    (label_dir / "pairs.csv").write_text("Image_1,Image_2,Human Preference\nr0.png,r1.png,\n")
    (label_dir / "renders.csv").write_text("image,psnr\nr0.png,20\n")
    with pytest.raises(UserError, match=r"^hpgs label: .*renders\.csv") as info:
        ls.Label(label_dir, oracle="psnr").main()
    assert "\n" not in str(info.value) and "lpips" in str(info.value)
    with pytest.raises(UserError, match=r"^hpgs label: --order uncertain needs --model"):
        ls.Label(label_dir, order="uncertain").main()


def test_order_uncertain_shows_least_sure_pairs_first(label_dir):
    import torch

    from hpgs_ns.preference.model import PreferenceModel

    model = PreferenceModel("alexnet", input_size=32)
    torch.manual_seed(0)
    with torch.no_grad():
        model.head.weight.normal_()
    model.save(label_dir / "m.pt")
    book = ls.LabelBook(label_dir / "pairs.csv")
    ls.order_by_uncertainty(book, label_dir / "m.pt")
    load = lambda i, s: torch.from_numpy(np.asarray(Image.open(book.image_path(i, s)), dtype=np.float32) / 255).permute(2, 0, 1)[None]  # noqa: E731
    with torch.no_grad():
        p = [float(model.prob_worse(load(i, 1), load(i, 2))) for i in range(8)]
    sureness = [abs(p[i] - 0.5) for i in book.order]
    assert sorted(book.order) == list(range(8)) and sureness == sorted(sureness)
    assert book.state()["pair"]["id"] == book.order[0]


# --- hardening: bursts, bad input, paths outside the folder, ports ------------------------------------------

@pytest.fixture
def served(label_dir):
    """(book, port) of an in-process server on a free port; stopped after the test."""
    book = ls.LabelBook(label_dir / "pairs.csv")
    server = ls.LabelServer(("127.0.0.1", 0), ls.make_handler(book))
    threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
    yield book, server.server_address[1]
    server.shutdown()
    server.server_close()


def _raw(port: int, data: bytes, end: bool = True, timeout: float = 5.0) -> Tuple[int, dict, dict]:
    """Send `data` as is (and end the stream unless `end` is False); (status, headers, JSON body) of the reply."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(data)
        if end:
            s.shutdown(socket.SHUT_WR)
        reply = b""
        while b"\r\n\r\n" not in reply or len(reply.split(b"\r\n\r\n", 1)[1]) < _length(reply):
            chunk = s.recv(65536)
            if not chunk:
                break
            reply += chunk
    head, _, body = reply.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = dict(line.split(": ", 1) for line in lines[1:])
    return int(lines[0].split()[1]), headers, json.loads(body)


def _length(reply: bytes) -> int:
    match = re.search(rb"\r\nContent-Length: (\d+)\r\n", reply.split(b"\r\n\r\n", 1)[0] + b"\r\n")
    return int(match.group(1)) if match else 1 << 30


def _post_raw(port: int, body: bytes, path: str = "/api/label", extra: str = "") -> bytes:
    return (f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(body)}\r\n{extra}\r\n").encode() + body


def test_burst_of_50_label_posts_is_all_written_once(tmp_path):
    """50 clients connect and post while the server is not yet accepting (as when it is busy): the listen
    backlog holds them all, and every label lands in the CSV exactly once."""
    Image.new("RGB", (8, 8)).save(tmp_path / "a.png")
    with open(tmp_path / "pairs.csv", "w", newline="") as f:
        csv.writer(f).writerows([["Image_1", "Image_2", "Human Preference"]] + [["a.png", "a.png", ""]] * 50)
    book = ls.LabelBook(tmp_path / "pairs.csv")
    server = ls.LabelServer(("127.0.0.1", 0), ls.make_handler(book))
    port = server.server_address[1]
    assert server.request_queue_size >= 50 and server.workers >= 8
    sent, codes = threading.Barrier(51), [None] * 50

    def client(i: int) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
        try:
            conn.request("POST", "/api/label", json.dumps({"id": i, "value": str(i % 2)}),
                         {"Content-Type": "application/json"})
            sent.wait()
            codes[i] = conn.getresponse().status
        except (OSError, threading.BrokenBarrierError) as err:  # with a backlog of 5: connect timed out
            codes[i] = repr(err)
        finally:
            conn.close()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(50)]
    try:
        for t in threads:
            t.start()
        try:
            sent.wait(timeout=10)  # all 50 connected and sent before the first accept
        except threading.BrokenBarrierError:
            pass  # some could not connect: codes says which
        threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
        for t in threads:
            t.join(15)
    finally:
        server.shutdown()
        server.server_close()
    # each client's socket timeout (5 s) is the hang guard: a connection the backlog dropped, or an answer that
    # never came, is its repr in `codes`; how fast the burst is served is benchmarks/small_timings.py's (label_burst_50_s)
    assert codes == [200] * 50
    assert _labels(tmp_path / "pairs.csv") == [(i % 2, False) for i in range(50)]
    assert sorted(book.history) == list(range(50))  # each answer applied once


def test_oversized_body_is_refused_unread(served, label_dir):
    book, port = served
    before = (label_dir / "pairs.csv").read_bytes()
    # headers announcing 200 MB and no body, the stream left open: a server that waited for the body would answer
    # only after its own socket timeout, so the client's shorter one (a socket.timeout here) is the hang guard
    request = _post_raw(port, b"").replace(b"Content-Length: 0", b"Content-Length: 200000000")
    code, headers, body = _raw(port, request, end=False, timeout=ls.SOCKET_TIMEOUT / 2)
    assert (code, headers["Connection"]) == (413, "close") and "65536" in body["error"]
    # exactly at the limit is fine
    pad = ls.MAX_BODY - len(json.dumps({"id": 0, "value": "1", "pad": ""}))
    payload = json.dumps({"id": 0, "value": "1", "pad": "x" * pad}).encode()
    assert len(payload) == ls.MAX_BODY
    assert _raw(port, _post_raw(port, payload))[0] == 200
    # one byte over: refused on the headers alone (a client that sent the body too may see a reset instead)
    assert _raw(port, _post_raw(port, payload + b" ")[:-len(payload) - 1], end=False)[0] == 413
    assert _labels(label_dir / "pairs.csv")[0] == (1, False) and before != (label_dir / "pairs.csv").read_bytes()


DEEP = b"[" * 30_000 + b"]" * 30_000  # under the body limit, far over json's recursion limit
BAD_REQUESTS = [  # (request bytes, with {port}; expected status)
    (b'{"id": Infinity, "value": "1"}', 400),
    (b'{"id": NaN, "value": "1"}', 400),
    (b'{"id": 1e999, "value": "1"}', 400),
    (b'{"id": ' + DEEP + b', "value": "1"}', 400),
    (b'{"id": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", 413),
    (b"[0, 1]", 400),
    (b"{not json", 400),
    (b'{"id": "\xff\xfe", "value": "1"}', 400),
    (b'{"id": ' + b"9" * 5000 + b', "value": "1"}', 400),
    (b'{"id": 0}', 400),
    ("GET /img/\u00b2/1 HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode("latin-1"), 404),
    ("GET /img/\u00b2/1 HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode("utf-8"), 404),
    (b"GET /img/99999999999999999999/1 HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n", 404),
    (b"GET /img/0/3 HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n", 404),
    (b"POST /api/label HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\nContent-Length: -5\r\n\r\n", 400),
    (b"POST /api/label HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\nContent-Length: 12\r\n\r\n{}", 400),
    (b"POST /api/label HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n", 411),
    (b"PUT /api/label HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n", 501),
    (b"HELLO\r\n\r\n", 400),
    (b"GET /" + b"a" * 70_000 + b" HTTP/1.0\r\n\r\n", 414),
]


def test_bad_requests_get_json_errors_and_no_traceback(served, label_dir, capfd):
    book, port = served
    before = (label_dir / "pairs.csv").read_bytes()
    for request, expected in BAD_REQUESTS:
        if not request[:5].isupper():  # a JSON body for /api/label
            request = _post_raw(port, request)
        if expected == 413:  # headers only: the refused body would meet a closed socket
            request = request[:request.index(b"\r\n\r\n") + 4]
        code, headers, body = _raw(port, request.replace(b"{port}", str(port).encode()), end=expected != 413)
        assert (code, headers["Content-Type"], set(body)) == (expected, "application/json", {"error"}), request[:60]
    assert (label_dir / "pairs.csv").read_bytes() == before
    # the server still serves, and printed nothing
    assert _raw(port, f"GET /api/state HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())[2]["labelled"] == 0
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")


def test_server_faults_are_json_500s_and_one_line(served, monkeypatch, capfd):
    book, port = served
    monkeypatch.delenv("HPGS_TRACEBACK", raising=False)

    def full_disk():
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(book, "save", full_disk)
    code, _, body = _raw(port, _post_raw(port, b'{"id": 0, "value": "1"}'))
    assert code == 500 and body["error"].startswith("could not save") and "No space left" in body["error"]
    monkeypatch.setattr(book, "state", lambda: 1 / 0)
    code, _, body = _raw(port, f"GET /api/state HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    assert (code, body) == (500, {"error": "internal error: ZeroDivisionError: division by zero"})
    err = capfd.readouterr().err
    assert err == "hpgs label: GET '/api/state' failed: ZeroDivisionError: division by zero\n"


def test_ids_must_be_integers_in_range(served, label_dir):
    book, port = served
    before = (label_dir / "pairs.csv").read_bytes()
    for pair_id in (2.7, 2.0, True, False, "2", -1, 8, None, [2], {"id": 2}):
        code, _, body = _raw(port, _post_raw(port, json.dumps({"id": pair_id, "value": "1"}).encode()))
        assert code == 400 and "id must be an integer 0..7" in body["error"], pair_id
    for value in (True, 2, "2", "yes", None, 1.0):
        code, _, body = _raw(port, _post_raw(port, json.dumps({"id": 2, "value": value}).encode()))
        assert code == 400 and "value must be" in body["error"], value
    assert (label_dir / "pairs.csv").read_bytes() == before and book.history == []
    code, _, state = _raw(port, _post_raw(port, b'{"id": 2, "value": 0}'))  # an integer value is fine
    assert (code, state["labelled"]) == (200, 1)
    assert _labels(label_dir / "pairs.csv")[:4] == [(None, False), (None, False), (0, False), (None, False)]


def test_images_are_served_only_from_inside_the_folder(tmp_path):
    collect = tmp_path / "collect"
    (collect / "sub").mkdir(parents=True)
    Image.new("RGB", (8, 8), (200, 0, 0)).save(collect / "sub" / "ok.png")
    secret = tmp_path / "secret.png"
    secret.write_bytes(b"not for the browser")
    (collect / "link.png").symlink_to(secret)
    names = ["../secret.png", "../../../../../../../" + str(secret), str(secret), "link.png",
             "sub/../sub/ok.png", "missing.png", "sub"]
    with open(collect / "pairs.csv", "w", newline="") as f:
        csv.writer(f).writerows([["Image_1", "Image_2", "Human Preference"]] + [[n, "sub/ok.png", ""] for n in names])
    book = ls.LabelBook(collect / "pairs.csv")
    assert [book.served_image(i, 1)[0] for i in range(len(names))] == [403, 403, 403, 403, 200, 404, 404]
    server = ls.LabelServer(("127.0.0.1", 0), ls.make_handler(book))
    threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    try:
        codes = []
        for i in range(len(names)):
            try:
                with urllib.request.urlopen(f"{url}img/{i}/1", timeout=10) as r:
                    codes.append(r.status)
                    assert r.read() == (collect / "sub" / "ok.png").read_bytes()
            except urllib.error.HTTPError as err:
                codes.append(err.code)
                reply = err.read()
                assert b"not for the browser" not in reply and "error" in json.loads(reply)
        assert codes == [403, 403, 403, 403, 200, 404, 404]
    finally:
        server.shutdown()
        server.server_close()


def test_stale_temp_files_are_removed_at_start_and_nothing_else(label_dir):
    stale = []
    for _ in range(2):  # atomic_write's own naming
        fd, tmp = tempfile.mkstemp(prefix=".pairs.csv.", suffix=".tmp", dir=label_dir)
        os.close(fd)
        stale.append(Path(tmp))
    keep = [".pairs.csv.notes.tmp", ".renders.csv.abcd1234.tmp", "pairs.csv.abcd1234.tmp",
            ".pairs.csv.abcd1234.tmp.bak"]
    for name in keep:
        (label_dir / name).write_text("keep")
    book = ls.LabelBook(label_dir / "pairs.csv")
    assert sorted(book.removed_temp_files) == sorted(stale)
    assert not any(p.exists() for p in stale) and all((label_dir / n).read_text() == "keep" for n in keep)
    assert ls.LabelBook(label_dir / "pairs.csv").removed_temp_files == []


def test_port_errors_are_one_line(label_dir):
    # the command line (started first: it imports torch meanwhile): exit 1, one line on stderr, no traceback
    env = {k: v for k, v in os.environ.items() if k != "HPGS_TRACEBACK"}
    proc = subprocess.Popen(_cli(label_dir, "--port", "99999"), cwd=REPO, env={**env, "PYTHONPATH": str(REPO)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for port in (99999, 65536, -1):
        with pytest.raises(UserError, match=rf"^hpgs label: --port {port} is out of range 0-65535"):
            ls.Label(label_dir, port=port)
    with pytest.raises(UserError, match=r"--port 99999 is out of range 0-65535"):  # tyro runs __post_init__
        tyro.cli(ls.Label, args=[str(label_dir), "--port", "99999"])
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        in_use = rf"^hpgs label: port {port} is in use; pick another with --port"
        with pytest.raises(UserError, match=in_use) as info:
            ls.Label(label_dir, port=port, open_browser=False).main()
        assert "\n" not in str(info.value)
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, out) == (1, "")
    assert err == "error: hpgs label: --port 99999 is out of range 0-65535 (0 picks a free one)\n"


# --- the page in a real headless Chromium ------------------------------------------------------------------

def test_label_page_in_headless_chromium(label_dir):
    sync_playwright = playwright_or_skip()
    book = ls.LabelBook(label_dir / "pairs.csv")
    server = ls.LabelServer(("127.0.0.1", 0), ls.make_handler(book))
    threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    args = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run"]
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=args)
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            external = []
            page.on("request", lambda r: None if r.url.startswith(url) else external.append(r.url))
            page.goto(url)
            page.wait_for_selector("body[data-ready='1']")
            page.wait_for_function("document.getElementById('img2').complete && document.getElementById('img2').naturalWidth > 0")
            # both images side by side and large
            box1, box2 = page.locator("#img1").bounding_box(), page.locator("#img2").bounding_box()
            assert box1["x"] + box1["width"] <= box2["x"] and box1["width"] > 500 and box1["height"] > 400
            assert page.locator("#img1").evaluate("e => e.naturalWidth") == 64
            assert "0 labelled, 0 skipped, 8 to go" in page.inner_text("#progress")
            page.screenshot(path="/tmp/hpgs_label_page.png")

            def press(key: str, pair_id: str) -> None:
                page.keyboard.press(key)
                page.wait_for_function(f"document.body.dataset.pairId === '{pair_id}'")

            press("1", "1")
            press("2", "2")
            press("s", "3")
            assert _labels(label_dir / "pairs.csv")[:4] == [(1, False), (0, False), (None, True), (None, False)]
            assert "2 labelled, 1 skipped, 5 to go" in page.inner_text("#progress")
            press("u", "2")  # undo the skip
            assert _labels(label_dir / "pairs.csv")[2] == (None, False)
            for i in range(2, 8):
                press("2", str(i + 1) if i < 7 else "")
            assert page.locator("#done").is_visible()
            assert [label for label, _ in _labels(label_dir / "pairs.csv")] == [1] + [0] * 7
            assert external == []  # no external assets
            browser.close()
    finally:
        server.shutdown()
        server.server_close()
    shot = np.asarray(Image.open("/tmp/hpgs_label_page.png").convert("RGB"))
    assert shot.shape[:2] == (720, 1280) and shot.std() > 10


# --- undo after a restart: the page promises only what the server can undo ------------------------------------

def test_undo_after_a_restart_says_there_is_nothing_to_undo_and_changes_nothing(label_dir):
    book = ls.LabelBook(label_dir / "pairs.csv")
    for i in range(len(book.rows)):
        book.answer(i, "1")
    restarted = ls.LabelBook(label_dir / "pairs.csv")  # `hpgs label` started again: this session answered nothing
    server = ls.LabelServer(("127.0.0.1", 0), ls.make_handler(restarted))
    threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        before = (label_dir / "pairs.csv").read_bytes()
        with urllib.request.urlopen(url + "/api/state", timeout=10) as r:
            state = json.loads(r.read())
        assert state["pair"] is None and state["can_undo"] is False
        undone = _post(url + "/api/undo", {})
        assert undone["note"] == ls.NOTHING_TO_UNDO and undone["can_undo"] is False
        assert (label_dir / "pairs.csv").read_bytes() == before
        restarted.answer(0, "0")  # an answer of this session is undone as before, without a note
        assert "note" not in _post(url + "/api/undo", {}) and _labels(label_dir / "pairs.csv")[0] == (None, False)
    finally:
        server.shutdown()
        server.server_close()


def _page_after(state: dict) -> dict:
    """What the page's script shows once it has fetched `state` (run in node, the DOM stubbed): display of the
    finished page's undo promise and of its note on earlier labels, and the status line."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (runs the page's script without a browser)")
    script = re.search(r"<script>(.*)</script>", ls.PAGE.read_text(), re.S).group(1)
    stub = """
const made = {};
const el = (id) => made[id] || (made[id] = {id, style: {}, textContent: "", dataset: {}, addEventListener() {}});
globalThis.document = {getElementById: el, addEventListener() {}, body: {dataset: {}}};
globalThis.fetch = async () => ({ok: true, json: async () => (STATE)});
""".replace("STATE", json.dumps(state))
    report = """
setTimeout(() => console.log(JSON.stringify({hint: el("undo-hint").style.display, earlier: el("earlier").style.display,
                                             status: el("status").textContent})), 50);
"""
    out = subprocess.run([node, "-e", stub + script + report], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_the_finished_page_promises_undo_only_when_this_session_can_undo():
    done = {"total": 8, "labelled": 8, "skipped": 0, "remaining": 0, "pair": None}
    assert _page_after({**done, "can_undo": True}) == {"hint": "inline", "earlier": "none", "status": ""}
    after_restart = _page_after({**done, "can_undo": False, "note": ls.NOTHING_TO_UNDO})
    assert (after_restart["hint"], after_restart["earlier"]) == ("none", "block")
    assert after_restart["status"] == "\u2014 " + ls.NOTHING_TO_UNDO
    page = ls.PAGE.read_text()
    assert re.search(r'<span id="undo-hint">[^<]*<kbd>u</kbd> undoes the last\s+label\)</span>', page)  # only in there
    assert page.count("undoes the last") == 1
