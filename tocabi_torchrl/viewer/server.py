"""Starting the viser server: the bind address and port, the URL to open, and the missing-extra error."""

from __future__ import annotations

import socket

from .extra import require_viser

__all__ = ["start_server", "page_url", "check_address"]


def page_url(host: str, port: int) -> str:
    """The URL a browser opens for a server bound to ``host``:``port`` (``0.0.0.0``/``::``: this machine's name,
    reachable from others; through an SSH tunnel open http://localhost:<port>). An IPv6 address goes in brackets
    (RFC 3986), or the browser reads its last group as the port.

    >>> page_url("127.0.0.1", 8080), page_url("::1", 8080)
    ('http://127.0.0.1:8080', 'http://[::1]:8080')
    """
    shown = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
    return f"http://[{shown}]:{port}" if ":" in shown else f"http://{shown}:{port}"


def check_address(host: str, port: int, option: str = "--viewer_port") -> None:
    """``ValueError`` unless the viewer can serve on ``host``:``port``: a port in [0, 65535] and a host that is an
    address of this machine. ``option``: where the port was set (``--viewer_port``, or ``viewer.port`` in a run's
    config), named in the error. viser, given another, tries a thousand ports and then waits for ever without saying so
    (a cloud machine's public address is a natural thing to type)."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"{option} must be an int in [0, 65535] (0: any free port), got {port!r}")
    found, last = [], OSError(f"{host!r} resolves to no address")
    try:
        found = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except OSError as err:  # socket.gaierror: a name that resolves to nothing
        last = err
    # The server binds every address the name resolves to and skips those it cannot: one that binds is enough
    # (localhost may resolve to ::1 first on a machine without IPv6).
    for family, _, _, _, address in found:
        try:
            with socket.socket(family, socket.SOCK_STREAM) as probe:
                probe.bind((address[0], 0, *address[2:]))  # any free port: whether the address is this machine's
            return
        except OSError as err:
            last = err
    raise ValueError(f"the viewer cannot serve on host {host!r} ({last.strerror or last}): use 127.0.0.1 (this "
                     "machine only; reach it via ssh -L) or 0.0.0.0 (every interface)") from None


#: Ports viser tries, from the one asked for upwards, before it gives up.
_VISER_TRIES = 1000


def _taken(host: str, port: int) -> bool:
    """Whether ``port`` on ``host`` cannot be bound now."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.bind((host, port))
        return False
    except OSError:
        return True


def start_server(host: str = "127.0.0.1", port: int = 8080, label: str = "tocabi-torchrl",
                 option: str = "--viewer_port"):
    """A running ``viser.ViserServer`` on ``host``:``port`` (raises :class:`~.extra.ViewerUnavailable` without the
    extra); ``option`` names where the port was set in its errors (``--viewer_port`` or ``viewer.port``). viser
    moves to the next free port when ``port`` is taken: the port it got is ``server.get_port()``."""
    check_address(host, port, option)
    # viser tries `port` and up to 999 ports after it; one past 65535 fails outside its retry and it then waits for
    # ever. Near the top of the range, refuse when every port left is taken (65534 with 65534 and 65535 taken hung).
    if port and port + _VISER_TRIES > 65536 and all(_taken(host, p) for p in range(port, 65536)):
        last = "and is the last port" if port == 65535 else "and so is every port after it up to 65535"
        raise ValueError(f"viewer port {port} is taken {last}, so no next one is free to move to: set another "
                         f"{option}")
    viser = require_viser()
    server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    server.gui.configure_theme(control_width="large", show_share_button=False)
    return server
