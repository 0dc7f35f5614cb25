"""Headless Chromium for tests that look at HTML the way a person would.

``ensure_chromium()`` returns the browser path. If ``/usr/bin/chromium`` (or another chromium on
PATH) is missing it tries ``apt-get install -y chromium`` (only as root with apt available,
bounded in time) and otherwise skips the calling test with the reason. The browser never uses
the network: the pages are local files and the flags switch off every background service.

``browser()`` drives the same system Chromium through Playwright (the [test] extra; Playwright's
own browser download is never used) for pages that must be clicked: console errors and page
errors are collected and any request off this machine is aborted and recorded.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

_CANDIDATES = ("/usr/bin/chromium", "chromium", "chromium-browser", "google-chrome")
_INSTALL_TIMEOUT_S = 900
_RUN_TIMEOUT_S = 120

_CHECK_SCRIPT = """
<script>
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  var d = document.createElement("div");
  d.id = "kf-image-check";
  d.textContent = "images=" + imgs.length + " loaded=" + ok;
  document.body.appendChild(d);
});
</script>
"""


def find_chromium() -> str | None:
    """Path of a Chromium binary, or None."""
    for c in _CANDIDATES:
        p = shutil.which(c) if not c.startswith("/") else (c if os.access(c, os.X_OK) else None)
        if p:
            return p
    return None


def _try_install() -> str:
    """Try ``apt-get install -y chromium``; return a reason string when it cannot."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "not running as root, cannot apt-get install chromium"
    if shutil.which("apt-get") is None:
        return "apt-get not available to install chromium"
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    cmd = ["apt-get", "install", "-y", "-qq", "--no-install-recommends", "chromium"]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=_INSTALL_TIMEOUT_S, env=env)
        if r.returncode != 0 and "Unable to locate package" in (r.stderr + r.stdout):
            subprocess.run(
                ["apt-get", "update", "-qq"],
                capture_output=True,
                text=True,
                timeout=_INSTALL_TIMEOUT_S,
                env=env,
            )
            r = subprocess.run(
                cmd, capture_output=True, text=True, timeout=_INSTALL_TIMEOUT_S, env=env
            )
    except subprocess.TimeoutExpired:
        return f"apt-get install chromium did not finish within {_INSTALL_TIMEOUT_S} s"
    except OSError as exc:
        return f"apt-get install chromium failed to start: {exc}"
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or [""]
        return f"apt-get install chromium failed (exit {r.returncode}): {tail[0]}"
    return ""


def ensure_chromium() -> str:
    """Return a Chromium path, installing the Debian package if possible; else skip the test."""
    path = find_chromium()
    if path:
        return path
    reason = _try_install()
    path = find_chromium()
    if path:
        return path
    pytest.skip(f"headless Chromium unavailable: {reason or 'chromium not found after install'}")


def _base_args(user_data_dir: str) -> list[str]:
    return [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-extensions",
        "--disable-default-apps",
        "--no-default-browser-check",
        "--disable-dev-shm-usage",
        f"--user-data-dir={user_data_dir}",
    ]


def _run(browser: str, extra: list[str], url: str) -> subprocess.CompletedProcess:
    """Run headless Chromium once. A run that printed the whole DOM (``--dump-dom``) and then
    hung on exit (seen on a loaded 2-core machine: it waits on D-Bus) counts as done with
    that output; any other timeout is raised."""
    with tempfile.TemporaryDirectory(prefix="kf-chromium-") as profile:
        args = [browser, *_base_args(profile), *extra, url]
        try:
            return subprocess.run(args, capture_output=True, text=True, timeout=_RUN_TIMEOUT_S)
        except subprocess.TimeoutExpired as exc:
            out = exc.stdout or b""
            out = out.decode("utf-8", "replace") if isinstance(out, bytes) else out
            if "--dump-dom" not in extra or "</html>" not in out:
                raise
            return subprocess.CompletedProcess(args, -9, out, "")


def count_loaded_images(browser: str, html_path: Path) -> tuple[int, int]:
    """Load a copy of ``html_path`` with a check script; return ``(n_images, n_loaded)``.

    An image counts as loaded when ``complete`` and ``naturalWidth > 0`` after the load event.
    """
    html = Path(html_path).read_text(encoding="utf-8")
    probe = (
        html.replace("</body>", _CHECK_SCRIPT + "</body>")
        if "</body>" in html
        else html + _CHECK_SCRIPT
    )
    with tempfile.TemporaryDirectory(prefix="kf-page-") as d:
        page = Path(d) / "probe.html"
        page.write_text(probe, encoding="utf-8")
        r = _run(browser, ["--dump-dom", "--virtual-time-budget=15000"], page.as_uri())
    m = re.search(r'id="kf-image-check">images=(\d+) loaded=(\d+)<', r.stdout)
    if not m:
        raise AssertionError(
            f"Chromium did not report images (exit {r.returncode}); stderr tail: {r.stderr[-800:]}"
        )
    return int(m.group(1)), int(m.group(2))


def screenshot(
    browser: str, html_path: Path, png_path: Path, *, width: int = 1280, height: int = 4000
) -> Path:
    """Screenshot of ``html_path`` (a tall window captures most of a report) to ``png_path``."""
    png_path = Path(png_path).resolve()
    r = _run(
        browser,
        [
            f"--screenshot={png_path}",
            f"--window-size={width},{height}",
            "--hide-scrollbars",
            "--virtual-time-budget=15000",
        ],
        Path(html_path).resolve().as_uri(),
    )
    if not png_path.is_file():
        raise AssertionError(
            f"Chromium wrote no screenshot (exit {r.returncode}); stderr tail: {r.stderr[-800:]}"
        )
    return png_path


# WebGL in headless Chromium without a GPU: SwiftShader (software), enabled explicitly
_PLAYWRIGHT_ARGS = [
    "--no-sandbox",
    "--disable-quic",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-default-apps",
    "--no-first-run",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]


def _local(url: str) -> bool:
    return url.startswith(("file:", "data:", "blob:", "about:")) or url.startswith(
        ("http://127.0.0.1:", "http://127.0.0.1/")
    )


@contextlib.contextmanager
def browser(*, width: int = 1280, height: int = 900, extra_args=()):
    """A Playwright browser context on the system Chromium (no browser download).

    Yields ``(context, log)``: new pages opened with ``context.new_page()`` record console
    errors and uncaught page errors in ``log["errors"]``; every request that is not to a
    local file or to 127.0.0.1 is aborted and recorded in ``log["blocked"]``. Skips the
    calling test when Playwright or Chromium is missing. ``extra_args``: more Chromium flags.
    """
    path = ensure_chromium()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:  # the [test] extra installs it
        pytest.skip("the Python package playwright is not installed (pip install -e '.[test]')")
    log: dict[str, list] = {"errors": [], "blocked": []}

    def watch(page):
        page.on(
            "console",
            lambda m: (
                log["errors"].append(f"console {m.type}: {m.text}") if m.type == "error" else None
            ),
        )
        page.on("pageerror", lambda e: log["errors"].append(f"page error: {e}"))

    def route(r):
        if _local(r.request.url):
            r.continue_()
        else:
            log["blocked"].append(r.request.url)
            r.abort()

    with sync_playwright() as pw:
        b = pw.chromium.launch(
            executable_path=path, args=[*_PLAYWRIGHT_ARGS, *extra_args], headless=True
        )
        try:
            ctx = b.new_context(viewport={"width": width, "height": height})
            ctx.on("page", watch)
            ctx.route("**/*", route)
            yield ctx, log
        finally:
            b.close()


def canvas_stats(png_bytes: bytes) -> dict:
    """Pixel statistics of a screenshot: ``non_white`` fraction and ``colors`` (distinct RGB)."""
    import io

    import numpy as np
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png_bytes)).convert("RGB")).reshape(-1, 3)
    non_white = float(np.mean(np.any(img < 245, axis=1)))
    return {"non_white": non_white, "colors": len(np.unique(img, axis=0)), "pixels": img}


def color_fraction(pixels, hex_color: str, tol: int = 40) -> float:
    """Fraction of ``pixels`` (N, 3) within ``tol`` (per channel) of ``hex_color``."""
    import numpy as np

    c = np.array([int(hex_color[i : i + 2], 16) for i in (1, 3, 5)])
    return float(np.mean(np.all(np.abs(pixels.astype(int) - c) <= tol, axis=1)))
