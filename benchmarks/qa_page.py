"""The QA page's size and open time: MB per sample on disk and the time headless Chromium takes
to load `index.html` in a fresh browser (navigation start to the load event: the script has
built every row and the thumbnails of the first screen have loaded; median of 3), for pages of
64 and 500 samples of the demo recipe (512 px).

    .venv/bin/python benchmarks/qa_page.py [--sizes 64 500] [--work DIR]

Needs Debian's chromium and chromium-driver (`make browser`) and selenium (the test extra).
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from dofsynth.cli import main as dofsynth

ROOT = Path(__file__).resolve().parents[1]


def make_set(work: Path, n: int) -> Path:
    """The demo recipe with `n` test samples (no train split)."""
    text = (ROOT / "recipes" / "demo.toml").read_text().replace("samples = { train = 56, test = 8 }",
                                                               f"samples = {{ train = 0, test = {n} }}")
    recipe = work / f"demo-{n}.toml"
    recipe.write_text(text.replace('name = "demo"', f'name = "demo-{n}"'))
    out = work / f"set-{n}"
    if not (out / "manifest.json").is_file():
        assert dofsynth(["generate", str(recipe), "--out", str(out), "--workers", "2", "--resume", "-q"]) == 0
    return out


def open_time(page: Path) -> float:
    """Seconds from navigation start to the load event, in a fresh browser (a browser that has
    shown a large page before is slower to show the next one: not what a reviewer sees)."""
    driver = browser()
    try:
        driver.get(page.as_uri())
        for _ in range(600):
            t = driver.execute_script("const t = performance.getEntriesByType('navigation')[0];"
                                      "return t.loadEventEnd > 0 ? t.loadEventEnd - t.startTime : null;")
            if t is not None:
                return float(t) / 1000.0
            time.sleep(0.05)
        raise TimeoutError(f"{page}: no load event within 30 s")
    finally:
        driver.quit()


def browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1920,1080"):
        opts.add_argument(a)
    return webdriver.Chrome(service=Service(shutil.which("chromedriver") or "/usr/bin/chromedriver"), options=opts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 500])
    ap.add_argument("--work", type=Path, default=None, help="keep the sets here (default: a temp folder)")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="qa-page-"))
    work.mkdir(parents=True, exist_ok=True)
    print("| samples | page folder MB | MB per sample | index.html MB | open s (median of 3) |")
    print("|---|---|---|---|---|")
    for n in args.sizes:
        out = make_set(work, n)
        page_dir = work / f"page-{n}"
        shutil.rmtree(page_dir, ignore_errors=True)
        assert dofsynth(["sheet", str(out), "--html", str(page_dir), "--n", str(n), "--sweep", "3", "-q"]) == 0
        size = sum(p.stat().st_size for p in page_dir.rglob("*") if p.is_file()) / 2**20
        index = (page_dir / "index.html").stat().st_size / 2**20
        t = statistics.median(open_time(page_dir / "index.html") for _ in range(3))
        print(f"| {n} | {size:.1f} | {size / n:.3f} | {index:.2f} | {t:.2f} |", flush=True)


if __name__ == "__main__":
    main()
