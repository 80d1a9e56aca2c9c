"""The live view's web server: a page, its assets (from this package) and ``/api/state``.

It runs in a process of its own (a fresh interpreter that holds none of the
recorder's files or ports, and runs nothing of the caller's main module), so that
serving pages never takes the recorder's interpreter lock: the recorder only writes
into the shared :class:`~tissuecli.live.state.LiveState`, and the server reads it. Inside, the
standard library's :class:`http.server.ThreadingHTTPServer` gives each connection a
thread; a page polls ``/api/state``; a browser that stops reading holds only its own
thread, which gives up after :data:`SOCKET_TIMEOUT_S`. The server's process ends with
the recorder's: on :meth:`LiveServer.close`, or when the pipe to the recorder reads
end-of-file or its parent changes (the recorder died), closing its socket as it goes.
"""

from __future__ import annotations

import errno
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Collection
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any

from ..core.errors import InputError
from .state import LiveState

#: where ``--live`` without a value listens: this machine only, a free port
DEFAULT_HOST = "127.0.0.1"
#: a connection that neither sends nor reads for this long is closed, s
SOCKET_TIMEOUT_S = 5.0
#: longest wait for the server's process to start and listen, s
START_TIMEOUT_S = 60.0
#: the server's process checks that the recorder is alive at least this often, s
PARENT_CHECK_S = 0.5
#: the server's process runs this much nicer than the recorder: where the two want
#: one core, the recorder has it
SERVER_NICE = 10
#: open connections served at once; one more is answered 503 with a Retry-After and
#: closed (a page holds one or two; a flood of slow connections holds no more threads)
MAX_CONNECTIONS = 32
#: what a refused connection is told to wait before asking again, s
RETRY_AFTER_S = 2
#: names a page may reach this server by besides the address it listens on: anything
#: else (a DNS name that an attacker's page rebinds to this machine) gets 403
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})

#: name in the URL -> (file in tissuecli/live/assets, content type)
ASSETS = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/live.js": ("live.js", "text/javascript; charset=utf-8"),
    "/live.css": ("live.css", "text/css; charset=utf-8"),
    "/uPlot.iife.min.js": ("uPlot.iife.min.js", "text/javascript; charset=utf-8"),
    "/uPlot.min.css": ("uPlot.min.css", "text/css; charset=utf-8"),
    "/uPlot.LICENSE": ("uPlot.LICENSE", "text/plain; charset=utf-8"),
}


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (or ``:PORT``, or ``[::1]:PORT``) to a host and a port (0: any free).

    Raises
    ------
    InputError
        If the text is not of that form or the port is not in 0-65535.
    """
    example = "e.g. 127.0.0.1:8050, or --live alone for a free port on 127.0.0.1"
    host, sep, port = text.strip().rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise InputError(f"--live expects HOST:PORT ({example}); got {text!r}")
    host = host.strip("[]") or DEFAULT_HOST
    return host, int(port)


def is_loopback(host: str) -> bool:
    """Whether an address to listen on reaches this machine alone."""
    import ipaddress

    if host.lower().rstrip(".") in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        try:
            return all(
                ipaddress.ip_address(info[4][0]).is_loopback
                for info in socket.getaddrinfo(host, None)
            )
        except (OSError, ValueError):
            return False


def exposure_warning(url: str) -> str | None:
    """One line for a server that listens beyond this machine (the page has no
    authentication: anyone who can reach the address sees the recording); None on
    loopback."""
    from urllib.parse import urlsplit

    host = urlsplit(url).hostname or ""
    if is_loopback(host):
        return None
    return (
        f"warning: the live view listens on {host}, beyond this machine, without "
        "authentication: anyone who can reach it sees the recording; use --live alone "
        "(127.0.0.1) unless that is meant"
    )


def allowed_host(header: str | None, bound: Collection[str]) -> bool:
    """Whether a request's ``Host`` header names this server.

    Allowed: the address it listens on, ``localhost``, the loopback addresses and,
    when it listens on every interface, any IP literal or this machine's own name. A
    DNS name of someone else's (a page that rebinds its name to this machine to read
    the recording) is not. No header (HTTP/1.0) is allowed: browsers always send one.
    """
    import ipaddress

    if header is None:
        return True
    name = header.strip().lower()
    if name.startswith("["):  # [::1]:8050
        name = name[1 : name.find("]")] if "]" in name else name
    elif name.count(":") == 1:
        name = name.rsplit(":", 1)[0]
    name = name.rstrip(".")
    names = {b.strip("[]").lower() for b in bound}
    if name in LOOPBACK_NAMES or name in names:
        return True
    if names & {"0.0.0.0", "::", ""}:
        try:
            ipaddress.ip_address(name)
            return True  # an IP literal cannot be rebound
        except ValueError:
            return name in {socket.gethostname().lower(), socket.getfqdn().lower()}
    return False


def load_asset(name: str) -> bytes:
    """The bytes of one file of the page, from the installed package."""
    return resources.files(__package__).joinpath("assets", name).read_bytes()


class LiveServer:
    """Serves the live view of ``state`` at ``host:port`` from a process of its own,
    until :meth:`close`.

    The socket is bound on construction (the call returns once the server's process
    listens), so that a port in use is refused before a recording begins.

    Parameters
    ----------
    state : LiveState
        What the page shows; the server's process attaches to its shared block.
    host : str
        Address to listen on.
    port : int
        Port; 0 picks a free one.

    Raises
    ------
    InputError
        If the address cannot be listened on (port in use, unknown host, no permission).
    """

    def __init__(self, state: LiveState, host: str = DEFAULT_HOST, port: int = 0) -> None:
        self.state = state
        fd, session, capacity = state.handle
        # two pipes: ours to it (end-of-file when this process ends, however it ends),
        # and its one line back (where it listens, or why it cannot)
        order_r, self._order = os.pipe()
        reply, reply_w = os.pipe()
        root = str(Path(__file__).resolve().parents[2])  # this package, whatever sys.path
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            p for p in (root, os.environ.get("PYTHONPATH", "")) if p
        )}  # fmt: skip
        code = "import sys; from tissuecli.live.server import main; main(sys.argv[1:])"
        args = [str(a) for a in (fd, capacity, order_r, reply_w, os.getpid(), host, port)]
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-c", code, *args, session],
                pass_fds=(fd, order_r, reply_w),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                env=env,
            )
        except BaseException:
            os.close(self._order)
            raise
        finally:
            os.close(order_r)
            os.close(reply_w)
        try:
            line = _read_line(reply, START_TIMEOUT_S)
        finally:
            os.close(reply)
        kind, _, value = line.partition(" ")
        if kind != "listening":
            self.close()
            raise InputError(
                value if kind == "error"
                else f"--live {host}:{port}: the live view's server did not start"
            )  # fmt: skip
        bound_host, bound_port = value.rsplit(" ", 1)
        self.address = (bound_host, int(bound_port))

    @property
    def url(self) -> str:
        host, port = self.address
        shown = f"[{host}]" if ":" in str(host) else str(host)
        return f"http://{shown}:{port}/"

    def start(self) -> LiveServer:
        """The server serves from construction on; for use as a context manager."""
        return self

    def close(self) -> None:
        """Stop serving: the server's process closes its socket and ends."""
        if self._order >= 0:
            os.close(self._order)  # end-of-file: stop
            self._order = -1
        try:
            self.process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:  # stuck: its socket goes with it
            self.process.kill()
            self.process.wait()

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def _read_line(fd: int, timeout_s: float) -> str:
    """One line from ``fd``, or what came before end-of-file or the timeout."""
    data = b""
    deadline = time.monotonic() + timeout_s
    while not data.endswith(b"\n"):
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            break
        chunk = os.read(fd, 4096)
        if not chunk:
            break
        data += chunk
    return data.decode(errors="replace").strip()


def main(argv: list[str]) -> None:
    """The server's process: map the state, listen, tell the recorder where, serve
    until the recorder closes its pipe (to stop, or because it died) or is gone.

    ``argv``: the shared block's descriptor, the ring's capacity, the order and reply
    pipes' descriptors, the recorder's process id, host, port, session.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the recorder's; it stops us
    if hasattr(os, "nice"):
        os.nice(SERVER_NICE)
    fd, capacity, order, reply, parent = (int(a) for a in argv[:5])
    host, port, session = argv[5], int(argv[6]), argv[7]
    state = LiveState(session, capacity=capacity, fd=fd)
    assets = {path: (load_asset(file), kind) for path, (file, kind) in ASSETS.items()}
    handler = type("Handler", (_Handler,), {"state": state, "assets": assets})
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    server_class = type("Server", (_Server,), {"address_family": family})
    try:
        httpd = server_class((host, port), handler)
    except OSError as exc:
        os.write(reply, f"error {_bind_problem(host, port, exc)}\n".encode())
        return
    bound = httpd.server_address
    handler.hosts = (host, str(bound[0]))
    os.write(reply, f"listening {bound[0]} {bound[1]}\n".encode())
    os.close(reply)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.1})
    thread.daemon = True
    thread.start()
    try:
        # the recorder never writes: the pipe becomes readable at end-of-file
        while os.getppid() == parent and not select.select([order], [], [], PARENT_CHECK_S)[0]:
            pass
    finally:
        httpd.shutdown()
        httpd.server_close()
        state.close()


def _bind_problem(host: str, port: int, exc: OSError) -> str:
    where = f"--live {host}:{port}"
    if exc.errno == errno.EADDRINUSE:
        return f"{where}: the port is in use; choose another, or give --live alone for a free one"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return f"{where}: no permission to listen there (ports below 1024 need root)"
    if isinstance(exc, socket.gaierror) or exc.errno == errno.EADDRNOTAVAIL:
        return f"{where}: this machine has no such address; use 127.0.0.1"
    return f"{where}: cannot listen there ({exc.strerror or exc})"


class _Server(ThreadingHTTPServer):
    daemon_threads = True  # a stalled page never keeps the recorder from exiting
    allow_reuse_address = False  # a port in use is refused, not shared
    request_queue_size = 64
    _open = 0
    _lock = threading.Lock()

    def process_request(self, request: Any, client_address: Any) -> None:
        """A thread per connection up to :data:`MAX_CONNECTIONS`; beyond, 503 at once."""
        with self._lock:
            full = self._open >= MAX_CONNECTIONS
            if not full:
                self._open += 1
        if full:
            _refuse_busy(request)
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            with self._lock:
                self._open -= 1
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._lock:
                self._open -= 1


def _refuse_busy(request: socket.socket) -> None:
    """503 with a Retry-After, written without waiting for the request: a busy server
    reads nothing from a connection it will not serve."""
    body = b"too many connections to the live view; retry shortly\n"
    head = (
        "HTTP/1.1 503 Service Unavailable\r\n"
        f"Retry-After: {RETRY_AFTER_S}\r\n"
        "Content-Type: text/plain; charset=utf-8\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    )
    try:
        request.settimeout(0.2)  # a client that does not read is not waited for
        request.sendall(head.encode() + body)
        # read what the client already sent, so that closing sends no reset that
        # would discard the answer before it is read
        request.setblocking(False)
        for _ in range(16):
            if not request.recv(65536):
                break
    except OSError:
        pass


class _Handler(BaseHTTPRequestHandler):
    state: LiveState
    assets: dict[str, tuple[bytes, str]]
    hosts: tuple[str, ...] = ()  # the address as given and as bound
    protocol_version = "HTTP/1.1"  # keep-alive: one connection per page
    timeout = SOCKET_TIMEOUT_S

    def do_GET(self) -> None:
        if not allowed_host(self.headers.get("Host"), self.hosts):
            self.close_connection = True
            self._send(
                b"forbidden: this page answers only to the address it listens on\n",
                "text/plain; charset=utf-8", code=403, cache=False,
            )  # fmt: skip
            return
        path = self.path.split("?", 1)[0]
        if path == "/api/state":
            self._send(self.state.document(), "application/json", cache=False)
        elif path in self.assets:
            body, kind = self.assets[path]
            self._send(body, kind, cache=True)
        else:
            self._send(b"not found\n", "text/plain; charset=utf-8", code=404, cache=False)

    def _send(self, body: bytes, kind: str, *, code: int = 200, cache: bool) -> None:
        self.send_response(code)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        # the page may load nothing from elsewhere
        self.send_header(
            "Content-Security-Policy",
            "default-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:",
        )
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        """Quiet: the recorder's status line owns the terminal."""

    def handle(self) -> None:
        try:
            super().handle()
        except (ConnectionError, TimeoutError):
            pass  # a page closed or stalled: its connection alone ends
