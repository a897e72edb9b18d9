"""`hpgs label`: answers saved before they are confirmed, survival of kill -9, resume, oracle, page in Chromium."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from http.server import ThreadingHTTPServer
from pathlib import Path
from typing import Optional

import numpy as np
import pytest
from conftest import CHROMIUM, playwright_or_skip
from PIL import Image

from hpgs_ns.errors import UserError
from hpgs_ns.preference import label_server as ls
from hpgs_ns.preference.pairs import read_pairs

REPO = Path(__file__).resolve().parents[1]
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
    proc = subprocess.Popen(
        [sys.executable, "-m", "hpgs_ns.cli", "label", str(label_dir), "--port", "0", "--no-open-browser"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    match = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
    assert match, f"no URL in {line!r}; stderr: {proc.stderr.read() if proc.poll() is not None else ''}"
    return proc, match.group(0)


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
    proc, url = _start_server(label_dir)  # resumes where it stopped
    try:
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


def test_oracle_noise_is_seeded(tmp_path, label_dir):
    runs = []
    for _ in range(2):
        d = tmp_path / f"copy{len(runs)}"
        shutil.copytree(label_dir, d, ignore=shutil.ignore_patterns("copy*"))
        ls.Label(d, oracle="lpips", noise=0.5, seed=3).main()
        runs.append([p.label for p in read_pairs(d / "pairs.csv")])
    assert runs[0] == runs[1]


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


# --- the page in a real headless Chromium ------------------------------------------------------------------

def test_label_page_in_headless_chromium(label_dir):
    sync_playwright = playwright_or_skip()
    book = ls.LabelBook(label_dir / "pairs.csv")
    server = ThreadingHTTPServer(("127.0.0.1", 0), ls.make_handler(book))
    threading.Thread(target=server.serve_forever, daemon=True).start()
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
