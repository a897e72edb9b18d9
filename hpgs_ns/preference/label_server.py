"""`hpgs label DIR`: label the pairs in DIR/pairs.csv in a browser page, or with an error oracle.

The page (static/label.html, no external assets) is served on 127.0.0.1 by the standard library's
http.server. Keys: 1 = the left image (Image_1) is worse (writes 1), 2 = the right one is (writes 0),
s = skip (Skipped = 1), u = undo the last answer of this session. Every answer is written to the CSV
(temporary file, fsync, rename) *before* the server confirms it, so killing the server loses no confirmed
label, and a restart resumes at the first pair without an answer.

`--oracle lpips|psnr|ssim` labels every open pair from DIR/renders.csv (columns image, psnr, ssim, lpips;
the worse image has the lower psnr/ssim or the higher lpips) without a browser, flipping each answer with
probability `--noise` (seeded): simulated labellers for experiments.

`--order uncertain --model M` shows first the pairs on which the model's p(Image_1 worse) is nearest 1/2.

Only this page may use the server: a request whose `Host` is not 127.0.0.1/localhost at the server's port (DNS
rebinding), or a POST whose `Origin` is another site (any page open in the same browser could otherwise post
labels), is refused with 403 and changes nothing.
"""

from __future__ import annotations

import csv
import json
import mimetypes
import random
import threading
import webbrowser
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Dict, List, Literal, Optional

import tyro
from typing_extensions import Annotated

from hpgs_ns.atomic_write import write_csv_atomic
from hpgs_ns.errors import UserError
from hpgs_ns.preference.model import CheckpointError
from hpgs_ns.preference.pairs import COLUMNS, SKIPPED, PairsError, pairs_reader, parse_flag

PAGE = Path(__file__).resolve().parent / "static" / "label.html"
LABEL, IMAGE_1, IMAGE_2 = COLUMNS[2], COLUMNS[0], COLUMNS[1]


class LabelBook:
    """The pairs CSV in memory: answers, the showing order, and atomic saves. Thread-safe."""

    def __init__(self, csv_path: Path):
        self.path = Path(csv_path)
        if not self.path.is_file():
            raise PairsError(f"{self.path}: pairs CSV not found; create it with `hpgs collect` "
                             f"(columns {','.join(COLUMNS)})")
        with open(self.path, newline="", encoding="utf-8-sig") as f:
            reader = pairs_reader(f, self.path)
            header = list(reader.fieldnames)
            self.rows: List[Dict[str, str]] = [dict(r) for r in reader]
        self.fields = header + ([SKIPPED] if SKIPPED not in header else [])
        for line, row in enumerate(self.rows, start=2):
            if None in row or not (row.get(IMAGE_1) or "").strip() or not (row.get(IMAGE_2) or "").strip():
                raise PairsError(f"{self.path}:{line}: malformed row (empty image name or extra cells); fix it")
            row[IMAGE_1], row[IMAGE_2] = row[IMAGE_1].strip(), row[IMAGE_2].strip()
            label = parse_flag(row.get(LABEL), self.path, line, LABEL)
            row[LABEL] = "" if label is None else str(label)
            row[SKIPPED] = "1" if parse_flag(row.get(SKIPPED), self.path, line, SKIPPED) == 1 else ""
        self.order = list(range(len(self.rows)))
        self.history: List[int] = []
        self.lock = threading.Lock()

    def is_open(self, i: int) -> bool:
        return self.rows[i][LABEL] == "" and self.rows[i][SKIPPED] != "1"

    def image_path(self, i: int, side: int) -> Path:
        return self.path.parent / self.rows[i][IMAGE_1 if side == 1 else IMAGE_2]

    def state(self) -> dict:
        """Counts and the next open pair (None when all are answered)."""
        labelled = sum(r[LABEL] != "" for r in self.rows)
        skipped = sum(r[SKIPPED] == "1" and r[LABEL] == "" for r in self.rows)
        nxt = next((i for i in self.order if self.is_open(i)), None)
        pair = None
        if nxt is not None:
            row = self.rows[nxt]
            pair = {"id": nxt, "image_1": row[IMAGE_1], "image_2": row[IMAGE_2],
                    "image_1_url": f"/img/{nxt}/1", "image_2_url": f"/img/{nxt}/2"}
        return {"total": len(self.rows), "labelled": labelled, "skipped": skipped,
                "remaining": len(self.rows) - labelled - skipped, "pair": pair, "can_undo": bool(self.history)}

    def save(self) -> None:
        write_csv_atomic(self.path, self.fields, self.rows)

    def answer(self, i: int, value: str) -> None:
        """value "1" (Image_1 worse), "0" (Image_2 worse) or "skip"; saved before returning."""
        if value not in ("1", "0", "skip"):
            raise ValueError(f"answer must be 1, 0 or skip, not {value!r}")
        with self.lock:
            if not 0 <= i < len(self.rows):
                raise ValueError(f"no pair {i}")
            row = self.rows[i]
            row[LABEL], row[SKIPPED] = ("", "1") if value == "skip" else (value, "")
            self.history.append(i)
            self.save()

    def undo(self) -> Optional[int]:
        """Clear the last answer given in this session (and save); returns its row or None."""
        with self.lock:
            if not self.history:
                return None
            i = self.history.pop()
            self.rows[i][LABEL], self.rows[i][SKIPPED] = "", ""
            # show it next, wherever the order had put it
            self.order.remove(i)
            self.order.insert(0, i)
            self.save()
            return i


def _read_renders(directory: Path) -> Dict[str, Dict[str, float]]:
    path = directory / "renders.csv"
    if not path.is_file():
        raise PairsError(f"{path}: not found; --oracle needs renders.csv (image, psnr, ssim, lpips) from `hpgs collect`")
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.DictReader(f)
        need = ["image", "psnr", "ssim", "lpips"]
        missing = [c for c in need if c not in (reader.fieldnames or [])]
        if missing:
            raise PairsError(f"{path}: missing column(s) {', '.join(missing)}; expected {','.join(need)}")
        try:
            return {r["image"].strip(): {m: float(r[m]) for m in need[1:]} for r in reader}
        except (TypeError, ValueError) as err:
            raise PairsError(f"{path}: non-numeric metric ({err}); fix or regenerate it with `hpgs collect`") from None


def oracle_label(book: LabelBook, metric: str, noise: float, seed: int) -> int:
    """Answer every open pair from the ground-truth error; returns how many were labelled. Saves once."""
    errors = _read_renders(book.path.parent)
    rng = random.Random(seed)
    count = 0
    for i, row in enumerate(book.rows):
        if not book.is_open(i):
            continue
        a, b = row[IMAGE_1], row[IMAGE_2]
        for name in (a, b):
            if name not in errors:
                raise PairsError(f"{book.path.parent / 'renders.csv'}: no row for {name}; regenerate it with `hpgs collect`")
        ea, eb = errors[a][metric], errors[b][metric]
        worse_1 = ea > eb if metric == "lpips" else ea < eb  # LPIPS: higher is worse; PSNR/SSIM: lower
        if ea == eb:
            worse_1 = rng.random() < 0.5
        if rng.random() < noise:
            worse_1 = not worse_1
        row[LABEL] = "1" if worse_1 else "0"
        count += 1
    book.save()
    return count


def order_by_uncertainty(book: LabelBook, model_path: Path, device: str = "cpu") -> None:
    """Open pairs sorted by |p(Image_1 worse) - 1/2| under the model (least sure first); others keep their place."""
    import torch

    from hpgs_ns.preference.evaluate import raw_features_of
    from hpgs_ns.preference.model import PreferenceModel

    model = PreferenceModel.load(model_path, device)
    open_rows = [i for i in book.order if book.is_open(i)]
    paths = list(dict.fromkeys(book.image_path(i, s) for i in open_rows for s in (1, 2)))
    with torch.no_grad():
        scores = model.score_features(model.standardise(raw_features_of(model, paths).to(device))).cpu()
    score = dict(zip(paths, scores.tolist()))
    sureness = {i: abs(torch.sigmoid(torch.tensor(score[book.image_path(i, 1)] - score[book.image_path(i, 2)])).item() - 0.5)
                for i in open_rows}
    book.order = sorted(open_rows, key=sureness.get) + [i for i in book.order if not book.is_open(i)]


def make_handler(book: LabelBook):
    """A request handler class bound to `book`."""

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, fmt, *args):  # keep the terminal quiet
            pass

        def _send(self, code: int, body: bytes, ctype: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, obj: dict, code: int = 200) -> None:
            self._send(code, json.dumps(obj).encode(), "application/json")

        def _foreign(self, post: bool) -> Optional[str]:
            """Why a request may not come from this page (refused), or None."""
            port = self.server.server_address[1]
            hosts = {f"127.0.0.1:{port}", f"localhost:{port}"}
            host = self.headers.get("Host", "")
            if host not in hosts:
                return f"Host {host!r} is not this server"
            origin = self.headers.get("Origin")
            # Browsers send Origin with every cross-site POST; a client without one (curl, a script) is local.
            if post and origin is not None and origin not in {f"http://{h}" for h in hosts}:
                return f"cross-site request from {origin} refused"
            return None

        def do_GET(self):
            if (why := self._foreign(post=False)) is not None:
                return self._json({"error": why}, 403)
            if self.path in ("/", "/index.html"):
                return self._send(200, PAGE.read_bytes(), "text/html; charset=utf-8")
            if self.path == "/api/state":
                with book.lock:
                    return self._json(book.state())
            parts = self.path.strip("/").split("/")
            if len(parts) == 3 and parts[0] == "img" and parts[1].isdigit() and parts[2] in ("1", "2"):
                i = int(parts[1])
                if i < len(book.rows):
                    path = book.image_path(i, int(parts[2]))  # only images the CSV names are served
                    if path.is_file():
                        ctype = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
                        return self._send(200, path.read_bytes(), ctype)
            self._json({"error": f"not found: {self.path}"}, 404)

        def do_POST(self):
            if (why := self._foreign(post=True)) is not None:
                return self._json({"error": why}, 403)
            try:
                length = int(self.headers.get("Content-Length") or 0)
                body = json.loads(self.rfile.read(length) or b"{}")
                if self.path == "/api/label":
                    book.answer(int(body["id"]), str(body["value"]))
                elif self.path == "/api/undo":
                    book.undo()
                else:
                    return self._json({"error": f"not found: {self.path}"}, 404)
            except (ValueError, KeyError, TypeError) as err:
                return self._json({"error": str(err)}, 400)
            except OSError as err:  # the save failed: the answer is not confirmed
                return self._json({"error": f"could not save {book.path}: {err}"}, 500)
            with book.lock:
                self._json(book.state())

    return Handler


@dataclass
class Label:
    """Label which render of each pair is worse: a browser page (keys 1/2/s/u), or an error oracle."""

    dir: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")]
    """Folder with pairs.csv and the images it names (and renders.csv for --oracle)."""
    pairs_csv: str = "pairs.csv"
    """Pairs file inside DIR."""
    oracle: Optional[Literal["lpips", "psnr", "ssim"]] = None
    """Label from ground-truth error in DIR/renders.csv instead of a person."""
    noise: float = 0.0
    """Oracle only: probability of flipping each answer."""
    seed: int = 0
    """Oracle only: seeds ties and flips."""
    order: Literal["file", "uncertain"] = "file"
    """Order the pairs are shown in; `uncertain` (needs --model) shows the model's least sure pairs first."""
    model: Optional[Path] = None
    """Preference model for --order uncertain."""
    port: int = 8765
    """Port on 127.0.0.1 (0 picks a free one)."""
    open_browser: bool = True
    """Open the page in the default browser."""

    def main(self) -> None:
        try:
            book = LabelBook(self.dir / self.pairs_csv)
            if self.oracle is not None:
                if not 0.0 <= self.noise <= 1.0:
                    raise PairsError(f"--noise must be in [0, 1], got {self.noise}")
                n = oracle_label(book, self.oracle, self.noise, self.seed)
                print(f"hpgs label: {n} pairs labelled by the {self.oracle} oracle (noise {self.noise:g}) -> {book.path}")
                return
            if self.order == "uncertain":
                if self.model is None:
                    raise PairsError("--order uncertain needs --model CHECKPOINT (from `hpgs train-pref`)")
                order_by_uncertainty(book, self.model)
        except (PairsError, CheckpointError) as err:
            raise UserError(f"hpgs label: {err}") from None
        server = ThreadingHTTPServer(("127.0.0.1", self.port), make_handler(book))
        url = f"http://127.0.0.1:{server.server_address[1]}/"
        state = book.state()
        print(f"hpgs label: {state['remaining']} of {state['total']} pairs to go; open {url} (Ctrl-C stops)", flush=True)
        if self.open_browser:
            webbrowser.open(url)
        try:
            server.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            server.server_close()
