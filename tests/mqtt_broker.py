"""A real mosquitto broker on a free loopback port, for the MQTT tests and benchmarks/bench_mqtt.py."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

EXE = shutil.which("mosquitto") or next((p for p in ("/usr/sbin/mosquitto",) if Path(p).exists()), None)
MISSING = "mosquitto is not installed (Debian package mosquitto: scripts/install-system-deps as root)"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Mosquitto:
    """``mosquitto -c`` with its own config in ``directory``; persistence on, so a restart keeps sessions.

    ``users``: name -> password (a password file; anonymous clients refused), else anonymous access.
    """

    def __init__(self, directory: Path, users: dict[str, str] | None = None) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.proc: subprocess.Popen | None = None
        lines = [f"listener {self.port} 127.0.0.1", f"persistence true", f"persistence_location {self.dir}/",
                 "autosave_interval 0", f"log_dest file {self.dir}/mosquitto.log", "user root"]
        if users:
            pwfile = self.dir / "passwd"
            pwfile.write_text("")
            for name, password in users.items():
                subprocess.run(["mosquitto_passwd", "-b", str(pwfile), name, password], check=True,
                               capture_output=True)
            lines += ["allow_anonymous false", f"password_file {pwfile}"]
        else:
            lines.append("allow_anonymous true")
        self.conf = self.dir / "mosquitto.conf"
        self.conf.write_text("\n".join(lines) + "\n")

    def start(self, timeout_s: float = 10.0) -> "Mosquitto":
        self.proc = subprocess.Popen([EXE, "-c", str(self.conf)], stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {self.proc.stderr.read().decode(errors='replace')}")
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.2).close()
                return self
            except OSError:
                time.sleep(0.02)
        raise RuntimeError(f"mosquitto did not listen on port {self.port} within {timeout_s} s")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()  # SIGTERM: mosquitto saves its persistence file and exits
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None


def wait_for(condition, timeout_s: float = 10.0, poll_s: float = 0.01) -> bool:
    """Poll ``condition()`` until it is true or ``timeout_s`` passed; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return bool(condition())
        time.sleep(poll_s)
    return True
