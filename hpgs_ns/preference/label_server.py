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

Hardening: a listen backlog and a fixed pool of worker threads absorb bursts of requests; request bodies over
64 KiB are refused (413) unread; every refusal or failure is answered as JSON `{"error": ...}` (no traceback
on the terminal for bad input); ids must be JSON integers in range; images are served only from inside DIR,
whatever the CSV names; temporary files left by a killed session are removed when the next one starts.
"""

from __future__ import annotations

import csv
import errno
import json
import mimetypes
import os
import queue
import random
import re
import sys
import threading
import traceback
import webbrowser
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple
from urllib.parse import urlsplit

import tyro
from typing_extensions import Annotated

from hpgs_ns.atomic_write import write_csv_atomic
from hpgs_ns.errors import UserError
from hpgs_ns.preference.pairs import COLUMNS, SKIPPED, PairsError, csv_errors, pairs_reader, parse_flag
from hpgs_ns.preference.recipe import PreferenceModelError  # not .model: `hpgs label --help` needs no torch

PAGE = Path(__file__).resolve().parent / "static" / "label.html"
LABEL, IMAGE_1, IMAGE_2 = COLUMNS[2], COLUMNS[0], COLUMNS[1]
MAX_BODY = 64 * 1024  # a label POST is ~30 bytes; anything near this is not the page
LISTEN_BACKLOG = 128  # connections the kernel queues while the workers are busy (socketserver's default: 5)
WORKERS = 32  # handler threads; saves are serialised by the book's lock anyway
SOCKET_TIMEOUT = 10.0  # seconds a client may stall mid-request before its worker is freed
NOTHING_TO_UNDO = ("nothing to undo: u undoes this session's answers only; to label a pair saved earlier again, clear "
                   "its Human Preference cell in pairs.csv")


def stale_temp_files(csv_path: Path) -> List[Path]:
    """Temporary files of atomic_write's pattern (`.NAME.XXXXXXXX.tmp`, mkstemp's 8 random characters) beside
    `csv_path`: a session killed mid-save leaves one; nothing else matches."""
    pattern = re.compile(rf"\.{re.escape(csv_path.name)}\.[a-z0-9_]{{8}}\.tmp")
    try:
        names = os.listdir(csv_path.parent)
    except OSError:
        return []
    return sorted(csv_path.parent / n for n in names if pattern.fullmatch(n) and (csv_path.parent / n).is_file())


class LabelBook:
    """The pairs CSV in memory: answers, the showing order, and atomic saves. Thread-safe."""

    def __init__(self, csv_path: Path):
        self.path = Path(csv_path)
        if not self.path.is_file():
            raise PairsError(f"{self.path}: pairs CSV not found; create it with `hpgs collect` "
                             f"(columns {','.join(COLUMNS)})")
        with csv_errors(self.path), open(self.path, newline="", encoding="utf-8-sig") as f:
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
        # leftovers of a session killed mid-save (the CSV itself is whole: the rename is atomic)
        self.removed_temp_files = stale_temp_files(self.path)
        for tmp in self.removed_temp_files:
            tmp.unlink(missing_ok=True)

    def is_open(self, i: int) -> bool:
        return self.rows[i][LABEL] == "" and self.rows[i][SKIPPED] != "1"

    def image_path(self, i: int, side: int) -> Path:
        return self.path.parent / self.rows[i][IMAGE_1 if side == 1 else IMAGE_2]

    def served_image(self, i: int, side: int) -> Tuple[int, Optional[Path]]:
        """(200, path) for an image the server may send, else (403 or 404, None): only regular files inside the
        CSV's folder once symlinks and `..` are resolved, so a CSV naming ../../etc/passwd exposes nothing."""
        if not 0 <= i < len(self.rows):
            return 404, None
        root = self.path.parent.resolve()
        try:
            path = (root / self.rows[i][IMAGE_1 if side == 1 else IMAGE_2]).resolve()
        except (OSError, RuntimeError, ValueError):  # symlink loop, NUL byte
            return 404, None
        if not path.is_relative_to(root):
            return 403, None
        return (200, path) if path.is_file() else (404, None)

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
    with csv_errors(path), open(path, newline="", encoding="utf-8-sig") as f:
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


class _Refused(Exception):
    """A request answered with `code` and {"error": message}."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = code


def _no_constant(name: str):
    raise ValueError(f"{name} is not JSON")  # json.loads accepts NaN/Infinity by default


def _show(value, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def make_handler(book: LabelBook):
    """A request handler class bound to `book`."""

    class Handler(BaseHTTPRequestHandler):
        timeout = SOCKET_TIMEOUT  # a stalled client frees its worker
        default_request_version = "HTTP/1.0"  # errors for garbled request lines keep a status line and headers

        def log_message(self, fmt, *args):  # keep the terminal quiet
            pass

        def _send(self, code: int, body: bytes, ctype: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            if self.close_connection:
                self.send_header("Connection", "close")
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, obj: dict, code: int = 200) -> None:
            self._send(code, json.dumps(obj).encode(), "application/json")

        def send_error(self, code, message=None, explain=None):
            """http.server's own refusals (bad request line, headers too long, unknown method) as JSON too."""
            self.close_connection = True
            text = message or explain or self.responses.get(code, ("", "error"))[1]
            self._json({"error": text}, code)

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

        def _guarded(self, handle) -> None:
            """Run `handle`; whatever goes wrong, the client gets a JSON error, not a dropped connection."""
            try:
                handle()
            except _Refused as err:
                self._json({"error": str(err)}, err.code)
            except RecursionError:
                self._json({"error": "JSON nested too deeply"}, 400)
            except TimeoutError:
                self.close_connection = True
                self._json({"error": f"request not complete within {SOCKET_TIMEOUT:g} s"}, 408)
            except ConnectionError:  # the client hung up: nobody to answer
                self.close_connection = True
            except Exception as err:  # a bug or a broken disk, not the client: one line on the terminal
                print(f"hpgs label: {self.command} {_show(self.path, 80)} failed: {type(err).__name__}: {err}",
                      file=sys.stderr, flush=True)
                if os.environ.get("HPGS_TRACEBACK"):
                    traceback.print_exc()
                self.close_connection = True
                self._json({"error": f"internal error: {type(err).__name__}: {err}"}, 500)

        def do_GET(self):
            self._guarded(self._get)

        def do_POST(self):
            self._guarded(self._post)

        def _get(self) -> None:
            if (why := self._foreign(post=False)) is not None:
                raise _Refused(403, why)
            path = urlsplit(self.path).path
            if path in ("/", "/index.html"):
                return self._send(200, PAGE.read_bytes(), "text/html; charset=utf-8")
            if path == "/api/state":
                with book.lock:
                    state = book.state()
                return self._json(state)
            # ASCII digits only: str.isdigit() accepts "²", which int() refuses
            match = re.fullmatch(r"/img/([0-9]{1,9})/([12])", path)
            if match:
                code, image = book.served_image(int(match.group(1)), int(match.group(2)))
                if image is not None:
                    ctype = mimetypes.guess_type(image.name)[0] or "application/octet-stream"
                    return self._send(200, image.read_bytes(), ctype)
                if code == 403:
                    raise _Refused(403, f"{path}: the CSV names a file outside {book.path.parent}; not served")
            raise _Refused(404, f"not found: {_show(path, 80)}")

        def _body(self) -> dict:
            """The request's JSON object; refused (unread) when over MAX_BODY."""
            if self.headers.get("Transfer-Encoding"):
                self.close_connection = True
                raise _Refused(411, "send a Content-Length, not a chunked body")
            length = (self.headers.get("Content-Length") or "0").strip()
            if not length.isascii() or not length.isdigit():
                self.close_connection = True
                raise _Refused(400, f"bad Content-Length {_show(length)}")
            if int(length) > MAX_BODY:
                self.close_connection = True  # the body stays unread: this connection cannot carry another request
                raise _Refused(413, f"request body of {int(length)} bytes; the limit is {MAX_BODY}")
            raw = self.rfile.read(int(length))
            if len(raw) < int(length):
                self.close_connection = True
                raise _Refused(400, f"body ended after {len(raw)} of {int(length)} bytes")
            try:
                body = json.loads(raw or b"{}", parse_constant=_no_constant)
            except ValueError as err:  # includes bad UTF-8
                raise _Refused(400, f"body is not JSON: {err}") from None
            if not isinstance(body, dict):
                raise _Refused(400, f"body must be a JSON object, not {type(body).__name__}")
            return body

        def _post(self) -> None:
            if (why := self._foreign(post=True)) is not None:
                raise _Refused(403, why)
            path = urlsplit(self.path).path
            if path not in ("/api/label", "/api/undo"):
                raise _Refused(404, f"not found: {_show(path, 80)}")
            body = self._body()
            try:
                if path == "/api/label":
                    i, value = body.get("id"), body.get("value")
                    # bool is an int and 2.7 would truncate: only a JSON integer names a pair
                    if type(i) is not int or not 0 <= i < len(book.rows):
                        raise _Refused(400, f"id must be an integer 0..{len(book.rows) - 1}, got {_show(i)}")
                    if type(value) is int:
                        value = str(value)
                    if value not in ("1", "0", "skip"):
                        raise _Refused(400, f"value must be \"1\", \"0\" or \"skip\", got {_show(value)}")
                    book.answer(i, value)
                    undone = True
                else:
                    undone = book.undo() is not None
            except OSError as err:  # the save failed: the answer is not confirmed
                raise _Refused(500, f"could not save {book.path}: {err}") from None
            with book.lock:
                state = book.state()
            if not undone:  # the page says so instead of seeming to ignore the key
                state["note"] = NOTHING_TO_UNDO
            self._json(state)

    return Handler


class LabelServer(HTTPServer):
    """HTTPServer with a deep listen backlog and a fixed pool of daemon worker threads: a burst of requests
    queues instead of being reset, and a flood cannot start unbounded threads."""

    request_queue_size = LISTEN_BACKLOG
    allow_reuse_port = False  # a second server on a busy port must fail, not share it

    def __init__(self, address, handler, workers: int = WORKERS):
        self.workers = workers
        self._requests: queue.SimpleQueue = queue.SimpleQueue()
        super().__init__(address, handler)  # binds; an OSError here leaves no thread behind
        for k in range(workers):
            threading.Thread(target=self._work, name=f"hpgs-label-{k}", daemon=True).start()

    def process_request(self, request, client_address):
        self._requests.put((request, client_address))

    def _work(self) -> None:
        while (item := self._requests.get()) is not None:
            request, client_address = item
            try:
                self.finish_request(request, client_address)
            except Exception:
                self.handle_error(request, client_address)
            finally:
                self.shutdown_request(request)

    def handle_error(self, request, client_address):
        """A client that hung up or stalled is no news; anything else is one line (HPGS_TRACEBACK=1: the
        traceback), never socketserver's traceback per request."""
        err = sys.exc_info()[1]
        if isinstance(err, (ConnectionError, TimeoutError)):
            return
        if os.environ.get("HPGS_TRACEBACK"):
            traceback.print_exc()
        else:
            print(f"hpgs label: request from {client_address[0]} failed: {type(err).__name__}: {err}",
                  file=sys.stderr, flush=True)

    def server_close(self):
        super().server_close()
        for _ in range(self.workers):
            self._requests.put(None)


def open_server(port: int, book: LabelBook) -> LabelServer:
    """The server on 127.0.0.1:port; UserError (one line naming the port and the fix) if it cannot listen."""
    try:
        return LabelServer(("127.0.0.1", port), make_handler(book))
    except OverflowError:
        raise UserError(f"hpgs label: --port {port} is out of range 0-65535") from None
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise UserError(f"hpgs label: port {port} is in use; pick another with --port "
                            f"(0 picks a free one)") from None
        if err.errno == errno.EACCES:
            raise UserError(f"hpgs label: port {port} needs privileges; pick one above 1023 with --port") from None
        raise UserError(f"hpgs label: cannot listen on 127.0.0.1:{port} ({err.strerror}); "
                        f"pick another with --port") from None


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

    def __post_init__(self) -> None:
        # tyro runs this while parsing, so a bad --port is one line before anything loads
        if not 0 <= self.port <= 65535:
            raise UserError(f"hpgs label: --port {self.port} is out of range 0-65535 (0 picks a free one)")

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
        except (PairsError, PreferenceModelError) as err:
            raise UserError(f"hpgs label: {err}") from None
        server = open_server(self.port, book)
        url = f"http://127.0.0.1:{server.server_address[1]}/"
        state = book.state()
        removed = len(book.removed_temp_files)
        note = f" (removed {removed} temporary file(s) left by a killed session)" if removed else ""
        print(f"hpgs label: {state['remaining']} of {state['total']} pairs to go; open {url} (Ctrl-C stops){note}",
              flush=True)
        if self.open_browser:
            webbrowser.open(url)
        try:
            server.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            server.server_close()
