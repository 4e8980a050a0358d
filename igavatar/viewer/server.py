"""A viser server on the address the user asked for, or a one-line error.

    server = open_server("127.0.0.1", 8080, label="igavatar")
    url = server_url(server)

viser moves on to the next free port when the one asked for is busy; a user who typed
`--port 8080` (or a script that opens that address) must learn that instead, so the port is
checked first and the bound port compared after. Port 0 asks the system for a free one.
"""

from __future__ import annotations

import contextlib
import errno
import socket
import sys
from typing import TYPE_CHECKING

from igavatar.errors import InputError

if TYPE_CHECKING:
    import viser

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080


def check_port_free(host: str, port: int, flag: str = "--port") -> None:
    """InputError when `port` on `host` cannot be bound (in use, or not an address of this machine);
    `flag` is the option's name in the message."""
    if not 0 <= port <= 65535:
        raise InputError(f"{flag} {port}: expected 0 (any free port) to 65535")
    if port == 0:
        return
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        # As the server will (asyncio sets SO_REUSEADDR): a port in TIME_WAIT is free, a listener is not.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InputError(f"{flag} {port}: already in use on {host}; give another {flag}, or {flag} 0 for any free one") from None
            raise InputError(f"{flag} {port} on {host}: cannot listen there ({exc.strerror})") from None


def open_server(host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, label: str = "igavatar",
                flag: str = "--port") -> viser.ViserServer:
    """A started server bound to exactly host:port (any free port for 0); `flag` names the option in errors."""
    import viser  # here: `train` imports this module for its early port check, without --view

    check_port_free(host, port, flag)
    # viser prints its banner on stdout, where `--json` output goes: to stderr with the progress.
    with contextlib.redirect_stdout(sys.stderr):
        server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    if port and server.get_port() != port:  # taken between the check and the bind
        stop_server(server)
        raise InputError(f"{flag} {port}: already in use on {host}; give another {flag}, or {flag} 0 for any free one")
    return server


def stop_server(server: viser.ViserServer) -> None:
    """Stop it (its goodbye line on stderr, like its banner)."""
    with contextlib.redirect_stdout(sys.stderr):
        server.stop()


def server_url(server: viser.ViserServer) -> str:
    host = server.get_host()
    shown = "localhost" if host in ("127.0.0.1", "localhost") else host
    return f"http://{shown}:{server.get_port()}"
