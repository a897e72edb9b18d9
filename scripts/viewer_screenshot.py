"""Screenshot of `ns-viewer --load-config RUN/config.yml` in headless Chromium (docs/viewer-selection.png, shown in the README).

    python scripts/viewer_screenshot.py RUN/config.yml docs/viewer-selection.png --highlight 2

Opens the run as ns-viewer does (nerfstudio's Viewer on the checkpoint), points the browser's camera at all the
training cameras from above (`--azimuth`, `--elevation`, `--distance` in degrees / camera-ring radii), picks a round
in the selection panel, waits for the render, and saves the page. Needs playwright and /usr/bin/chromium.
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from pathlib import Path

import numpy as np

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]

# viser lowers the 3D canvas' pixel ratio to 0.2x devicePixelRatio while frames are slow, which software GL always
# is; reporting 5 keeps the canvas at >= 1 pixel per CSS pixel (the page's layout does not depend on it).
KEEP_FULL_RESOLUTION = "Object.defineProperty(window, 'devicePixelRatio', {get: () => 5})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("output", type=Path)
    parser.add_argument("--highlight", type=int, default=0, help="round to pick in the panel (0: none)")
    parser.add_argument("--azimuth", type=float, default=-90.0)
    parser.add_argument("--elevation", type=float, default=45.0)
    parser.add_argument("--distance", type=float, default=1.5)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=900)
    parser.add_argument("--wait", type=float, default=40.0, help="seconds for the CPU render to finish")
    parser.add_argument("--composite-depth", action=argparse.BooleanOptionalAction, default=True,
                        help="nerfstudio's 'Composite depth' (off: cameras show through floaters)")
    parser.add_argument("--colours", type=int, default=256, help="palette size of the saved PNG (0: full colour)")
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    args = parser.parse_args()

    from nerfstudio.utils.eval_utils import eval_setup
    from nerfstudio.viewer.viewer import Viewer
    from nerfstudio.viewer_legacy.server.viewer_utils import get_free_port
    from playwright.sync_api import sync_playwright

    from hpgs_ns.viewer import VISER_SCALE, round_label

    config, pipeline, _, step = eval_setup(args.config, test_mode="test")
    config.viewer.websocket_host, config.viewer.websocket_port = "127.0.0.1", get_free_port()
    config.viewer.default_composite_depth = args.composite_depth
    viewer = Viewer(config.viewer, log_filename=config.get_base_dir() / config.viewer.relative_log_filename,
                    datapath=pipeline.datamanager.get_datapath(), pipeline=pipeline, train_lock=threading.Lock())
    dm = pipeline.datamanager
    viewer.init_scene(train_dataset=dm.train_dataset, train_state="completed", eval_dataset=dm.eval_dataset)
    viewer.update_scene(step=step)

    centres = dm.train_dataset.cameras.camera_to_worlds[:, :3, 3].numpy() * VISER_SCALE
    centre = centres.mean(0)
    radius = float(np.linalg.norm(centres - centre, axis=1).max())
    az, el = math.radians(args.azimuth), math.radians(args.elevation)
    offset = args.distance * radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=args.chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": args.width, "height": args.height})
            page.add_init_script(KEEP_FULL_RESOLUTION)
            page.goto(f"http://127.0.0.1:{config.viewer.websocket_port}/")
            page.get_by_text("View selection").first.wait_for(timeout=60_000)
            for client in viewer.viser_server.get_clients().values():
                client.camera.up_direction = (0.0, 0.0, 1.0)
                client.camera.position = tuple(centre + offset)
                client.camera.look_at = tuple(centre)
            if args.highlight:
                page.get_by_label("Highlight").click()
                page.get_by_role("option", name=round_label(dm.history[args.highlight - 1])).click()
            # The panel scrolled to the selection folder.
            page.get_by_text("View selection").first.evaluate("e => e.scrollIntoView({block: 'start'})")
            time.sleep(args.wait)
            args.output.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(args.output))
            browser.close()
        if args.colours:
            # A dithered 256-colour PNG: ~3/4 of the size, with the role colours kept exact enough to match the legend.
            from PIL import Image

            image = Image.open(args.output).convert("RGB")
            palette = image.quantize(args.colours, method=Image.Quantize.FASTOCTREE)
            image.quantize(palette=palette, dither=Image.Dither.FLOYDSTEINBERG).save(args.output, optimize=True)
    finally:
        viewer.viser_server.stop()
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
