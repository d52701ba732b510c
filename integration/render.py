"""Pictures of a recording from rerun's own viewer, without a display.

    python benchmarks/render_recording.py RECORDING.rrd --at 1.0 [--at 2.0] [--out docs/img/sheet] \
        [--size 1600x1000] [--view scene] [--settle 8]

Starts rerun's native viewer headless (``rerun --headless``), bound to 127.0.0.1 on a free port, opens the
recording with its own blueprint, moves the time cursor to each ``--at`` time [s] on ``sim_time`` and saves a
screenshot of the whole viewer (or of one view, ``--view NAME``: "scene", "contacts", ...) to
``<out>_t<time>.png``; the viewer is shut down right after, also on errors.

Needs a Vulkan driver: on Debian/Ubuntu without a GPU, Mesa's software rasteriser (lavapipe) from
``apt-get install mesa-vulkan-drivers``. :func:`render` raises :class:`RenderUnavailable` where the viewer
cannot start (no rerun binary, no graphics adapter), so tests can skip cleanly.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence


class RenderUnavailable(RuntimeError):
    """The headless viewer could not start here (no rerun binary or no Vulkan adapter)."""


def _rerun_binary() -> str | None:
    """The viewer binary itself (rerun_cli's, not the Python launcher script, which would outlive a terminate)."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.exists():
            return str(exe)
    except ImportError:
        pass
    exe = Path(sys.executable).parent / "rerun"
    if exe.exists():
        return str(exe)
    return shutil.which("rerun")


def _stop(proc: subprocess.Popen) -> None:
    """Stop the viewer and everything it started (its own process group): SIGTERM, then SIGKILL after 10 s."""
    for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 10)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(wait)
            break
        except subprocess.TimeoutExpired:
            continue


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for_port(port: int, proc: subprocess.Popen, timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RenderUnavailable(f"the headless viewer exited with code {proc.returncode}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.2)
    raise RenderUnavailable(f"the headless viewer did not listen on 127.0.0.1:{port} within {timeout:.0f} s")


def render(recording: str | Path, times: Sequence[float], out: str | Path, size: str = "1600x1000",
           view: str | None = None, timeout: float = 60.0, settle: float = 8.0) -> list[Path]:
    """Screenshots (PNG files ``<out>_t<time>.png``) of ``recording`` at the sim_time ``times`` [s], taken by
    rerun's native viewer running headless on 127.0.0.1 (stopped before returning); ``view``: the name of one
    view to capture (default: the whole viewer, ``size`` WIDTHxHEIGHT pixels); ``settle`` [s]: wait before the
    first picture, until the viewer's start-up notifications have faded."""
    import rerun.experimental as rrx

    recording = Path(recording).resolve()
    if not recording.is_file():
        raise FileNotFoundError(f"no recording at {recording}")
    if not re.fullmatch(r"[1-9][0-9]*x[1-9][0-9]*", size):
        raise ValueError(f"size must be WIDTHxHEIGHT in pixels, e.g. 1600x1000, got {size!r}")
    exe = _rerun_binary()
    if exe is None:
        raise RenderUnavailable("the rerun binary (from rerun-sdk) is not on PATH")
    port = _free_port()
    log = tempfile.NamedTemporaryFile("w", prefix="rerun-headless-", suffix=".log", delete=False)
    proc = subprocess.Popen([exe, "--headless", "--bind", "127.0.0.1", "--port", str(port), "--hide-welcome-screen",
                             "--window-size", size, "--memory-limit", "2GiB"],
                            stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "RERUN_APP_ONLY": "true"},
                            start_new_session=True)  # its own process group: stopped whole by _stop
    paths = []
    try:
        _wait_for_port(port, proc, timeout)
        client = rrx.ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
        client.open(str(recording))
        deadline = time.monotonic() + timeout
        while client.get_state().loading and time.monotonic() < deadline:
            time.sleep(0.3)
        view_id = None
        if view is not None:
            deadline = time.monotonic() + timeout
            while view_id is None and time.monotonic() < deadline:
                state = client.get_state()
                view_id = next((v.view_id for v in state.views if v.name == view), None)
                time.sleep(0.5)
            if view_id is None:
                raise ValueError(f"no view named {view!r} in {recording.name}")
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        time.sleep(settle)  # the viewer's start-up notifications fade out
        for t in times:
            client.set_time("sim_time", duration=float(t), play_state="paused")
            time.sleep(1.0)  # let the viewer load and paint the frame
            png = client.take_screenshot(view_id)
            path = out.with_name(f"{out.name}_t{t:g}.png")
            path.write_bytes(png)
            paths.append(path)
    except RenderUnavailable:
        raise
    except Exception as exc:
        try:  # a viewer without a graphics adapter panics soon after it starts listening
            proc.wait(3)
        except subprocess.TimeoutExpired:
            pass
        log.flush()
        text = Path(log.name).read_text(errors="replace")
        if proc.poll() is not None or "graphics adapter" in text:
            raise RenderUnavailable(f"the headless viewer stopped ({exc}); its log: {log.name}") from exc
        raise
    finally:
        _stop(proc)
        log.close()
    Path(log.name).unlink(missing_ok=True)  # kept only when something went wrong
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recording")
    ap.add_argument("--at", type=float, action="append", required=True, help="sim_time [s] of a picture (repeat)")
    ap.add_argument("--out", default=None, help="path prefix of the PNGs (default: next to the recording)")
    ap.add_argument("--size", default="1600x1000", help="viewer window WIDTHxHEIGHT [px]")
    ap.add_argument("--view", default=None, help="capture only the view of this name, e.g. scene")
    ap.add_argument("--settle", type=float, default=8.0, help="seconds to wait before the first picture")
    args = ap.parse_args(argv)
    out = args.out or str(Path(args.recording).with_suffix(""))
    try:
        for p in render(args.recording, args.at, out, args.size, args.view, settle=args.settle):
            print(p)
    except RenderUnavailable as exc:
        print(f"cannot render: {exc}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
