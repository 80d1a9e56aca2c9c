"""The live view's web server: a page, its assets (from this package) and ``/api/state``.

Standard library only (:class:`http.server.ThreadingHTTPServer`): one thread per
connection, all of them apart from the recorder's acquisition loop, which only
appends to :class:`~tissuecli.live.state.LiveState`. A page polls ``/api/state``;
a browser that stops reading holds only its own thread, which gives up after
:data:`SOCKET_TIMEOUT_S`.
"""

from __future__ import annotations

import errno
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from ..core.errors import InputError
from .state import LiveState

#: where ``--live`` without a value listens: this machine only, a free port
DEFAULT_HOST = "127.0.0.1"
#: a connection that neither sends nor reads for this long is closed, s
SOCKET_TIMEOUT_S = 5.0

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


def load_asset(name: str) -> bytes:
    """The bytes of one file of the page, from the installed package."""
    return resources.files(__package__).joinpath("assets", name).read_bytes()


class LiveServer:
    """Serves the live view of ``state`` at ``host:port`` until :meth:`close`.

    The socket is bound on construction, so that a port in use is refused before a
    recording begins.

    Parameters
    ----------
    state : LiveState
        What the page shows.
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
        assets = {path: (load_asset(name), kind) for path, (name, kind) in ASSETS.items()}
        handler = type("Handler", (_Handler,), {"state": state, "assets": assets})
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        server_class = type("Server", (_Server,), {"address_family": family})
        try:
            self.httpd = server_class((host, port), handler)
        except OSError as exc:
            raise InputError(_bind_problem(host, port, exc)) from None
        self.thread = threading.Thread(
            target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True
        )

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        shown = f"[{host}]" if ":" in str(host) else str(host)
        return f"http://{shown}:{port}/"

    def start(self) -> LiveServer:
        self.thread.start()
        return self

    def close(self) -> None:
        """Stop serving and close the socket; pages left open say the recording ended."""
        if self.thread.is_alive():
            self.httpd.shutdown()
        self.httpd.server_close()

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


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


class _Handler(BaseHTTPRequestHandler):
    state: LiveState
    assets: dict[str, tuple[bytes, str]]
    protocol_version = "HTTP/1.1"  # keep-alive: one connection per page
    timeout = SOCKET_TIMEOUT_S

    def do_GET(self) -> None:
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
