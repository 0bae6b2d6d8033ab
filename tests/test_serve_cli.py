"""`python -m lab serve` as an operator starts it: it warns when it serves beyond this machine, says which port it
really bound when the one asked for is busy, and stops on Ctrl-C without a traceback."""
import signal
import socket
import subprocess
import sys
import time

from sims.scene.config import REPO_ROOT
from testing import browser
from testing.helpers import interruptible


def test_serve_warns_about_open_hosts_and_prints_the_port_it_really_bound(tmp_path):
    port = browser.free_port()
    busy = socket.socket()
    busy.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    busy.bind(("0.0.0.0", port))
    busy.listen()
    command = [sys.executable, "-m", "lab", "serve", str(REPO_ROOT / "scenes" / "default.yaml"), "--host", "0.0.0.0",
               "--port", str(port), "--arch", "cpu", "--set", "texture_size=32"]
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    with open(out, "w") as stdout, open(err, "w") as stderr:
        process = subprocess.Popen(command, cwd=REPO_ROOT, stdout=stdout, stderr=stderr, preexec_fn=interruptible)
        try:
            deadline = time.monotonic() + 240
            while "tissue lab: http://" not in out.read_text():
                assert process.poll() is None, f"serve exited early: {err.read_text()}"
                assert time.monotonic() < deadline, "serve never printed its URL"
                time.sleep(0.2)
            process.send_signal(signal.SIGINT)
            code = process.wait(timeout=60)
        finally:
            if process.poll() is None:
                process.kill()
            busy.close()
    printed, warned = out.read_text(), err.read_text()
    line = next(text for text in printed.splitlines() if text.startswith("tissue lab: http://"))
    bound = int(line.split("http://", 1)[1].split()[0].rsplit(":", 1)[1])
    assert bound != port, f"the busy port {port} was printed: {line}"
    assert f"port {port} is busy" in warned and f"port {bound}" in warned
    assert "--host 0.0.0.0" in warned and "reverse proxy" in warned
    assert code == 0 and "Traceback" not in warned, warned
