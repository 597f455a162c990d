"""The viewer at scale: ``seqvpr view`` of a 10k-query x 10k-reference match with images, each figure beside a
yardstick measured in the same run.

- write: the page written with thumbnails made (first run) and with thumbnails cached (second run), against the
  ``seqvpr match`` that made the run (the same process start-up, the same frames read);
- open: the page loaded in headless Chromium (the navigation's load event), against the same browser loading a
  page of the same size with no script (what the data alone costs);
- step: one ``seqvprView.step`` to the next frame and to the next failure, to the next painted frame (two
  animation frames), median of 50, against one empty animation-frame round trip.

Run from the repository root (CPU; about 10 minutes at 10k frames, most of it describing and thumbnailing):

    .venv/bin/python bench/bench_view.py --work runs/view-bench [--frames 10000]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import cpu_model

ROOT = Path(__file__).resolve().parents[1]
SEQVPR = [sys.executable, "-m", "seqvpr.cli"]


def write_images(folder: Path, n: int, seed: int, noise: float, detours: bool = False) -> None:
    """``n`` small JPEG frames of a smooth random 'route' (frame i looks like its neighbours), a metre apart; with
    ``detours``, one stretch of 20 frames in 200 shows somewhere else (queries that fail)."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    base = rng.random((n // 8 + 16, 48, 3))
    own = np.random.default_rng(seed)
    names = []
    for i in range(n):
        at = i / 8.0
        lo = int(at)
        strip = (1 - (at - lo)) * base[lo] + (at - lo) * base[lo + 1]
        if detours and (i // 20) % 10 == 3:
            strip = base[own.integers(len(base))]
        pixels = np.repeat(strip[None], 36, axis=0) + noise * own.random((36, 48, 3))
        image = Image.fromarray(np.clip(pixels * 200, 0, 255).astype(np.uint8)).resize((96, 72))
        name = f"{i:06d}.jpg"
        image.save(folder / name, quality=85)
        names.append(name)
    (folder / "positions.csv").write_text("name,easting,northing\n" + "".join(f"{n},0,{i}\n" for i, n in
                                                                             enumerate(names)))


def timed(arguments: list[str]) -> float:
    started = time.perf_counter()
    subprocess.run(arguments, check=True, cwd=ROOT, capture_output=True)
    return time.perf_counter() - started


def browser_figures(page: Path, blank: Path) -> dict[str, float]:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,1000"):
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    load = "const n = performance.getEntriesByType('navigation')[0]; return n.loadEventEnd - n.startTime;"
    painted = ("const done = arguments[arguments.length - 1]; const t0 = performance.now(); %s; "
               "requestAnimationFrame(() => requestAnimationFrame(() => done(performance.now() - t0)));")
    try:
        figures = {}
        for name, path in (("open", page), ("open blank", blank)):
            times = []
            for _ in range(3):
                driver.get(path.as_uri())
                times.append(driver.execute_script(load))
            figures[name] = float(np.median(times)) / 1e3
        driver.get(page.as_uri())
        for name, call in (("step", "seqvprView.step(1, false)"), ("next failure", "seqvprView.step(1, true)"),
                           ("empty frame", "0")):
            driver.execute_script("seqvprView.select(100)")
            figures[name] = float(np.median([driver.execute_async_script(painted % call) for _ in range(50)]))
        zoom = "const t0 = performance.now(); seqvprView.zoomMatrix(arguments[0]); return performance.now() - t0;"
        figures["zoom 4, tiles made"] = driver.execute_script(zoom, 4)
        figures["pan, tiles kept"] = float(np.median([driver.execute_script(zoom, 1.0001) for _ in range(20)]))
        return figures
    finally:
        driver.quit()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("runs/view-bench"))
    parser.add_argument("--frames", type=int, default=10_000)
    args = parser.parse_args()
    work = args.work.resolve()
    shutil.rmtree(work, ignore_errors=True)
    print(cpu_model(), flush=True)
    write_images(work / "ref", args.frames, 1, 0.05)
    write_images(work / "qry", args.frames, 2, 0.3, detours=True)
    match = timed([*SEQVPR, "match", "-r", str(work / "ref"), "-q", str(work / "qry"), "--radius", "5m", "-L", "5",
                   "--out", str(work / "run")])
    first = timed([*SEQVPR, "view", str(work / "run"), "--out", str(work / "page")])
    second = timed([*SEQVPR, "view", str(work / "run"), "--out", str(work / "page")])
    page = work / "page" / "index.html"
    blank = work / "blank.html"
    blank.write_text("<!doctype html><html><body><pre>" + "x" * page.stat().st_size + "</pre></body></html>")
    figures = browser_figures(page, blank)
    print(f"| frames | match s (yardstick) | view s, thumbnails made | view s, thumbnails cached | page MB |")
    print(f"| {args.frames:,} x {args.frames:,} | {match:.1f} | {first:.1f} | {second:.1f} | "
          f"{page.stat().st_size / 1e6:.1f} |")
    print("| open s | blank page of its size s | step ms | next failure ms | empty frame ms | zoom x4 ms (tiles "
          "made) | redraw ms (tiles kept) |")
    print(f"| {figures['open']:.2f} | {figures['open blank']:.2f} | {figures['step']:.1f} | "
          f"{figures['next failure']:.1f} | {figures['empty frame']:.1f} | {figures['zoom 4, tiles made']:.1f} | "
          f"{figures['pan, tiles kept']:.1f} |")


if __name__ == "__main__":
    main()
