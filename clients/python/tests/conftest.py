"""Fixtures: a real `mbnt serve` (binary from MBNT_BIN) on a free port with a fresh data directory."""

import contextlib
import os
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.request

import pytest

MBNT_BIN = os.environ.get("MBNT_BIN")

# Small limits: tiny fits end within seconds, and a limit is easy to hit on purpose.
LIMITS = {
    "--max-iterations": "50",
    "--max-frames": "8",
    "--max-points-per-frame": "5000",
    # Small, so that a JSON body over the limit is cheap to send (the server reads an
    # over-limit body to its end, up to 256 MiB, before it answers 413).
    "--max-json-bytes": "4096",
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running_server(token=None):
    """Start `mbnt serve` (one worker, one thread, small limits), yield its URL, stop it."""
    if not MBNT_BIN:
        pytest.skip("MBNT_BIN is not set: it must name an mbnt binary (e.g. target/release/mbnt)")
    work = tempfile.mkdtemp(prefix="mbnt-client-test-")
    port = _free_port()
    env = dict(os.environ, RUST_LOG="warn")
    env.pop("MBNT_API_TOKEN", None)
    if token is not None:
        env["MBNT_API_TOKEN"] = token
    args = [MBNT_BIN, "serve", "--bind", f"127.0.0.1:{port}", "--data-dir", os.path.join(work, "data"),
            "--workers", "1", "--threads-per-job", "1"]
    for option, value in LIMITS.items():
        args += [option, value]
    log = open(os.path.join(work, "server.log"), "wb")
    server = subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        ready = False
        for _ in range(100):
            try:
                urllib.request.urlopen(url + "/healthz", timeout=1)
                ready = True
                break
            except OSError:
                if server.poll() is not None:
                    break
                time.sleep(0.1)
        if not ready:
            log.flush()
            with open(os.path.join(work, "server.log"), encoding="utf-8", errors="replace") as f:
                pytest.fail(f"mbnt serve did not start:\n{f.read()}")
        yield url
    finally:
        server.terminate()
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
        log.close()
        shutil.rmtree(work, ignore_errors=True)


@pytest.fixture(scope="session")
def server_url():
    """URL of a server without a token, shared by the tests."""
    with running_server() as url:
        yield url
